#!/usr/bin/env python3
"""Drives instant-ngp through its Python module (pyngp) on a lent GPU machine, for
scripts/ingp_lease.sh (issue 57, item 2). Our code, written from instant-ngp's sources; it
needs pyngp, numpy and scipy (the lent machine's image has the last two).

  train   trains a NeRF-synthetic scene for --minutes of training time, as scripts/run.py
          trains by default (its default network, and its RflRelax schedule: NeRF mode before
          step 15000, RflRelax from 15000 to 30000, unless --train-mode nerf), and saves a
          snapshot at each whole minute (the clock stops while it saves).
  score   loads a snapshot (instant-ngp's or ours) and scores the views of a transforms file
          under run.py's protocol (black background, pixel centres, 8 samples a pixel, rays
          stopped at transmittance 1e-4, render and ground truth encoded to sRGB and
          clipped, PSNR per view averaged, its luminance SSIM); with --against DIR, also
          against our renders of the same views (`stegongp eval --out DIR`: rgb_NNN.png,
          8-bit, so agreement is capped near 59 dB).

Prints one JSON object on stdout.
"""

import argparse
import glob
import json
import os
import sys
import time

import numpy as np


def load_pyngp(build):
    """pyngp from the build folder (its .so lies at the top of the CMake build)."""
    found = glob.glob(os.path.join(build, "pyngp*.so"))
    if not found:
        sys.exit(f"ingp_driver: no pyngp*.so under {build} (was it built? see the build log)")
    sys.path.insert(0, build)
    import pyngp  # noqa: E402

    return pyngp


def testbed(ngp, src):
    t = ngp.Testbed()
    # The default network (configs/nerf/base.json) is found under root_dir, as run.py sets it.
    t.root_dir = src
    return t


def srgb(x):
    """scripts/common.py's encoding: exponent 1/2.4, the power branch strictly above the knee."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x > 0.0031308, 1.055 * np.power(np.maximum(x, 0.0031308), 1.0 / 2.4) - 0.055,
                    12.92 * x)


def ssim_luminance(a, b):
    """common.py's SSIM: Rec. 709 luminance, a separable 5-tap blur (scipy's 'reflect'
    edges), K1 0.01, K2 0.03, the map's mean. The same definition as
    crates/score/src/metrics.rs's ssim_instant_ngp."""
    from scipy.ndimage import convolve1d

    k = np.array([0.120078, 0.233881, 0.292082, 0.233881, 0.120078])

    def blur(x):
        return convolve1d(convolve1d(x, k, axis=0), k, axis=1)

    w = np.array([0.2126, 0.7152, 0.0722])
    la, lb = a @ w, b @ w
    ma, mb = blur(la), blur(lb)
    sa = blur(la * la) - ma * ma
    sb = blur(lb * lb) - mb * mb
    sab = blur(la * lb) - ma * mb
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    m = (2 * ma * mb + c1) / (ma * ma + mb * mb + c1) * (2 * sab + c2) / (sa + sb + c2)
    m[~np.isfinite(m)] = 0.0
    return float(m.mean())


def psnr(a, b):
    """(PSNR, MSE) of two images in [0, 1]; the MSE over pixels and channels, as run.py."""
    mse = float(np.mean((a - b) ** 2))
    return (float("inf") if mse == 0 else float(-10.0 * np.log10(mse))), mse


def train(a):
    ngp = load_pyngp(a.build)
    t = testbed(ngp, a.src)
    t.load_training_data(a.scene)
    t.shall_train = True
    nerf_mode, relax = ngp.TrainMode.Nerf, ngp.TrainMode.RflRelax
    os.makedirs(a.snapshots, exist_ok=True)
    marks = [m for m in range(1, int(a.minutes) + 1)]
    trained = 0.0
    checkpoints = []
    last = (0.0, 0)
    while marks:
        step = t.training_step
        if a.train_mode == "nerf":
            t.nerf.training.train_mode = nerf_mode
        else:
            t.nerf.training.train_mode = relax if 15000 <= step < 30000 else nerf_mode
        t0 = time.perf_counter()
        if not t.frame():
            sys.exit("ingp_driver: testbed.frame() returned false")
        trained += time.perf_counter() - t0
        if trained >= marks[0] * 60.0:
            m = marks.pop(0)
            path = os.path.join(a.snapshots, f"ingp_{m}min.ingp")
            t0 = time.perf_counter()
            t.save_snapshot(path, False)
            steps = t.training_step
            checkpoints.append({
                "minutes": m, "step": steps, "train_seconds": round(trained, 2),
                "steps_per_second": (steps - last[1]) / max(trained - last[0], 1e-9),
                "train_mode": str(t.nerf.training.train_mode), "loss": t.loss,
                "snapshot": path, "save_seconds": round(time.perf_counter() - t0, 2),
            })
            last = (trained, steps)
            print(f"[ingp] {m} min: step {steps}", file=sys.stderr, flush=True)
    print(json.dumps({
        "scene": a.scene, "train_mode_option": a.train_mode,
        # The target samples a step (run.py never changes it); instant-ngp adapts its rays a
        # batch to reach it, and pyngp exposes no measured count.
        "training_batch_size": t.training_batch_size,
        "checkpoints": checkpoints,
    }))


def score(a):
    ngp = load_pyngp(a.build)
    t = testbed(ngp, a.src)
    t.load_snapshot(a.snapshot)
    # run.py's scoring settings, read from its source (scripts/run.py 269-282).
    t.background_color = [0.0, 0.0, 0.0, 1.0]
    t.snap_to_pixel_centers = True
    t.nerf.render_min_transmittance = 1e-4
    t.shall_train = False
    t.load_training_data(a.test)
    t.render_with_lens_distortion = True
    spp = 8
    views = []
    t_start = time.perf_counter()
    n = t.nerf.training.dataset.n_images
    for i in range(n):
        res = t.nerf.training.dataset.metadata[i].resolution
        t.render_ground_truth = True
        t.set_camera_to_training_view(i)
        ref = t.render(res[0], res[1], 1, True)
        t.render_ground_truth = False
        t0 = time.perf_counter()
        img = t.render(res[0], res[1], spp, True)
        seconds = time.perf_counter() - t0
        A = np.clip(srgb(img[..., :3]), 0.0, 1.0)
        R = np.clip(srgb(ref[..., :3]), 0.0, 1.0)
        p, mse = psnr(A, R)
        v = {"index": i, "psnr": p, "mse": mse, "ssim": ssim_luminance(A, R),
             "render_seconds": round(seconds, 4)}
        if a.against:
            ours = os.path.join(a.against, f"rgb_{i:03d}.png")
            from PIL import Image

            with Image.open(ours) as im:
                o = np.asarray(im.convert("RGB"), dtype=np.float64) / 255.0
            # Both 8-bit, as ours is: the comparison is between what each program shows.
            q = np.round(A * 255.0) / 255.0
            v["psnr_vs_ours"] = psnr(q, o)[0]
        views.append(v)
    out = {
        "snapshot": a.snapshot, "test": a.test, "protocol": "instant-ngp (scripts/run.py)",
        "n_views": n, "spp": spp,
        "psnr": float(np.mean([v["psnr"] for v in views])),
        "ssim": float(np.mean([v["ssim"] for v in views])),
        "seconds": round(time.perf_counter() - t_start, 2),
        "views": views,
    }
    if a.against:
        out["psnr_vs_ours"] = float(np.mean([v["psnr_vs_ours"] for v in views]))
    print(json.dumps(out))


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--build", required=True, help="instant-ngp's CMake build folder")
    p.add_argument("--src", required=True, help="instant-ngp's source folder (configs/)")
    sub = p.add_subparsers(dest="what", required=True)
    pt = sub.add_parser("train")
    pt.add_argument("--scene", required=True, help="transforms_train.json")
    pt.add_argument("--minutes", type=float, default=5.0)
    pt.add_argument("--snapshots", required=True, help="folder for a snapshot a minute")
    pt.add_argument("--train-mode", choices=["run.py", "nerf"], default="run.py")
    ps = sub.add_parser("score")
    ps.add_argument("--snapshot", required=True)
    ps.add_argument("--test", required=True, help="transforms_test.json")
    ps.add_argument("--against", help="our renders of the same views (stegongp eval --out)")
    a = p.parse_args()
    train(a) if a.what == "train" else score(a)


if __name__ == "__main__":
    main()
