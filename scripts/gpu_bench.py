#!/usr/bin/env python3
"""The GPU benchmark in one command (issue 29): measure StegoNGP on a machine that has a GPU
but no Rust toolchain and no network, in one short run.

  prepare DIR   (here, on the developer's machine) builds the portable binary (x86-64-v3,
                stripped), recompresses lego's 100 training views and 8 test views to lossless
                WebP (checked pixel for pixel), downloads the Vulkan loader's .deb, and checks
                that DIR and the repository's tracked files fit in 64 MiB together.
  run DIR OUT   (there) installs the loader if the machine lacks one, expands the binary and
                the images, fails loudly unless it got a hardware adapter, prints the adapter
                and its limits, trains lego at 800x800 for 5 minutes (test PSNR at each
                minute; one step in 50 timed phase by phase on the device), trains the lego + text stego pair for 2 minutes beside a plain text
                model trained for the same steps (scored through its stored grid and through
                one rebuilt from the network, as the hidden scene's is), and writes OUT/gpu_bench.json (rewritten
                after every phase, so a run cut short keeps what it measured) and OUT/log.txt.

  prepare DIR --capture PATH
                carries a real capture instead of lego (any folder `train` reads, its files
                byte for byte; `--capture-skip` leaves out what the loader does not read);
                `run` then trains it on the GPU at `--capture-downscale` for `--capture-minutes`
                (held-out PSNR at each minute) and brings the model back in parts of at most
                15 MiB (what a lent machine returns), which `join` puts together again here.

`--small` makes both ends tiny (a generated scene instead of lego, seconds instead of
minutes, the software adapter allowed) so that the whole path runs in CI on llvmpipe
(tests/gpu_bench.rs). Needs Python 3 with Pillow at both ends.
"""

import argparse
import hashlib
import json
import lzma
import multiprocessing
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
LIMIT = 64 * 1024 * 1024
# A lent machine returns files of at most 16 MiB each, 8 of them and 64 MiB in all: the
# capture's model comes back in parts below that.
PART = 15 * 1024 * 1024
MAX_PARTS = 6
# The Vulkan loader, and the GL vendor-neutral dispatch (glvnd) libraries that NVIDIA's
# Vulkan driver (libGLX_nvidia) needs at run time: without them the loader finds the driver
# but "could not get 'vkCreateInstance'" from it, and no adapter is listed.
LOADER_DEBS = ["libvulkan1", "libglvnd0", "libglx0", "libegl1", "libgl1", "libopengl0",
               "libgles2"]
LOADER_LIBS = ["libvulkan.so.1", "libGLdispatch.so.0", "libGLX.so.0", "libEGL.so.1"]
NVIDIA_ICD = Path("/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json")


def fail(msg):
    print(f"gpu_bench: error: {msg}", file=sys.stderr)
    sys.exit(1)


def need_pillow():
    """Both ends convert images with Pillow: say so before minutes of building or setup,
    naming this interpreter (a version manager's python3 may lack what the system's has)."""
    try:
        import PIL.Image  # noqa: F401
    except ImportError:
        fail(f"{sys.executable} has no Pillow: run this script with a Python 3 that has it "
             "(Debian: apt-get install python3-pil, then /usr/bin/python3 scripts/gpu_bench.py ...)")


def tree_bytes(path):
    return sum(f.stat().st_size for f in Path(path).rglob("*") if f.is_file())


def tracked_bytes():
    """What travels with the repository: tracked files and untracked ones git does not ignore."""
    try:
        out = subprocess.run(
            ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
            cwd=REPO, check=True, capture_output=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        # Not a git checkout: every file but the build and the carry folders.
        skip = {"target", ".git", ".carry", ".carry-capture", "out"}
        return sum(f.stat().st_size for f in REPO.rglob("*")
                   if f.is_file() and not skip & set(f.relative_to(REPO).parts))
    total = 0
    for name in out.split(b"\0"):
        p = REPO / name.decode()
        if name and p.is_file():
            total += p.stat().st_size
    return total


# ---------------------------------------------------------------------------------------------
# prepare


def to_webp(job):
    """One PNG to lossless WebP; the decoded WebP must equal the PNG's pixels, alpha and the
    colour under transparent pixels included (`exact`)."""
    from PIL import Image

    src, dst = job
    with Image.open(src) as im:
        im.load()
        mode = "RGBA" if "A" in im.getbands() else "RGB"
        im = im.convert(mode)
        dst.parent.mkdir(parents=True, exist_ok=True)
        tmp = dst.with_suffix(".webp.tmp")
        im.save(tmp, "WEBP", lossless=True, quality=100, method=4, exact=True)
        with Image.open(tmp) as back:
            if back.convert(mode).tobytes() != im.tobytes():
                raise RuntimeError(f"{src}: WebP round trip is not lossless")
        os.replace(tmp, dst)
    return src.stat().st_size, dst.stat().st_size


def spread(n, k):
    """k indices spread evenly over n (all of them if k >= n)."""
    if k >= n:
        return list(range(n))
    return [round(i * n / k) for i in range(k)]


def prepare_scene(src, dst, test_views):
    """NeRF-synthetic `src` to `dst` with WebP images: every training view, `test_views` test
    views spread over the split."""
    jobs = []
    sizes = {}
    for split, pick in (("train", None), ("test", test_views)):
        meta = json.loads((src / f"transforms_{split}.json").read_text())
        frames = meta["frames"]
        if pick is not None:
            frames = [frames[i] for i in spread(len(frames), pick)]
        meta["frames"] = frames
        dst.mkdir(parents=True, exist_ok=True)
        (dst / f"transforms_{split}.json").write_text(json.dumps(meta, indent=1))
        sizes[split] = len(frames)
        for f in frames:
            rel = f["file_path"]
            png = src / (rel if rel.endswith(".png") else rel + ".png")
            out = dst / (rel[: -len(".png")] if rel.endswith(".png") else rel)
            jobs.append((png, out.with_suffix(".webp") if out.suffix else Path(str(out) + ".webp")))
    with multiprocessing.Pool(os.cpu_count()) as pool:
        pairs = pool.map(to_webp, jobs)
    png_bytes = sum(p for p, _ in pairs)
    webp_bytes = sum(w for _, w in pairs)
    return {"views": sizes, "png_bytes": png_bytes, "webp_bytes": webp_bytes}


def sha256_of(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def copy_capture(src, dst, skip):
    """Every file of the capture `src` into `dst`, byte for byte, but those under a
    relative path in `skip`; a digest of the whole (names and contents) says which capture
    a run measured."""
    if not src.is_dir():
        fail(f"{src}: no such capture folder")
    skip = [Path(s) for s in skip]
    for s in skip:
        if s.is_absolute() or ".." in s.parts or not (src / s).exists():
            fail(f"--capture-skip {s}: not a file or folder inside {src}")
    tree = hashlib.sha256()
    files = 0
    total = 0
    for f in sorted(src.rglob("*")):
        rel = f.relative_to(src)
        if any(rel.parts[: len(s.parts)] == s.parts for s in skip):
            continue
        if f.is_symlink():
            fail(f"{f}: a symbolic link; the capture must be plain files")
        if not f.is_file():
            continue
        out = dst / rel
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(f, out)
        tree.update(str(rel).encode() + b"\0" + sha256_of(out).encode() + b"\n")
        files += 1
        total += out.stat().st_size
    if files == 0:
        fail(f"{src}: no files to carry")
    return {"source": str(src), "files": files, "bytes": total,
            "skipped": [str(s) for s in skip], "sha256": tree.hexdigest()}


def build_portable():
    env = dict(os.environ, RUSTFLAGS="-C target-cpu=x86-64-v3")
    cmd = ["cargo", "build", "--profile", "portable", "--locked", "--target-dir",
           str(REPO / "target" / "portable"), "--bin", "stegongp"]
    print("+ RUSTFLAGS='-C target-cpu=x86-64-v3' " + " ".join(cmd), file=sys.stderr)
    subprocess.run(cmd, cwd=REPO, env=env, check=True)
    return REPO / "target" / "portable" / "portable" / "stegongp"


def download_loader(dst):
    """The Vulkan loader's .deb for amd64, as the device's README says to fetch it."""
    dst.mkdir(parents=True, exist_ok=True)
    lists = Path(tempfile.mkdtemp(prefix="gpu_bench_apt"))
    (lists / "partial").mkdir()
    opts = ["-oAPT::Architecture=amd64", "-oAPT::Architectures=amd64",
            f"-oDir::State::Lists={lists}"]
    subprocess.run(["apt-get", *opts, "update"], check=True, capture_output=True)
    subprocess.run(["apt-get", *opts, "download", *LOADER_DEBS], cwd=dst, check=True)
    shutil.rmtree(lists, ignore_errors=True)
    debs = sorted(p.name for p in dst.glob("*.deb"))
    if not debs:
        fail("apt-get download left no .deb")
    return debs


def prepare(a):
    need_pillow()
    t0 = time.time()
    d = Path(a.dir)
    if d.exists() and any(d.iterdir()):
        if not a.force:
            fail(f"{d}: not empty (--force replaces it)")
        shutil.rmtree(d)
    d.mkdir(parents=True, exist_ok=True)
    binary = Path(a.binary) if a.binary else build_portable()
    if not binary.is_file():
        fail(f"{binary}: no such binary")
    raw = binary.read_bytes()
    with lzma.open(d / "stegongp.xz", "wb", preset=1 if a.small else 9) as f:
        f.write(raw)
    manifest = {
        "binary": {"source": str(binary), "bytes": len(raw),
                   "sha256": hashlib.sha256(raw).hexdigest(),
                   "xz_bytes": (d / "stegongp.xz").stat().st_size},
        "small": a.small,
    }
    if a.capture:
        manifest["capture"] = copy_capture(Path(a.capture), d / "capture", a.capture_skip)
    else:
        lego = Path(a.lego)
        if not (lego / "transforms_train.json").is_file():
            fail(f"{lego}: no transforms_train.json (lego, or --lego DIR)")
        manifest["lego"] = prepare_scene(lego, d / "lego", a.test_views)
    if a.no_loader:
        manifest["loader"] = []
    else:
        manifest["loader"] = download_loader(d / "gl")
    (d / "manifest.json").write_text(json.dumps(manifest, indent=1))
    carried = tree_bytes(d)
    repo = tracked_bytes()
    manifest["carried_bytes"] = carried
    manifest["repository_bytes"] = repo
    (d / "manifest.json").write_text(json.dumps(manifest, indent=1))
    total = carried + repo
    print(json.dumps(manifest, indent=1))
    print(f"prepared {d} in {time.time() - t0:.0f} s: {carried / 2**20:.1f} MiB carried + "
          f"{repo / 2**20:.1f} MiB repository = {total / 2**20:.1f} MiB of 64", file=sys.stderr)
    if total > LIMIT:
        fail(f"{total} bytes: past the 64 MiB a run may carry")


# ---------------------------------------------------------------------------------------------
# run


def from_webp(job):
    from PIL import Image

    src, dst = job
    with Image.open(src) as im:
        im.save(dst, "PNG", compress_level=1)


def expand_scene(src, dst):
    jobs = []
    for webp in src.rglob("*.webp"):
        out = dst / webp.relative_to(src).with_suffix(".png")
        out.parent.mkdir(parents=True, exist_ok=True)
        jobs.append((webp, out))
    for meta in src.glob("transforms_*.json"):
        shutil.copy(meta, dst / meta.name)
    with multiprocessing.Pool(os.cpu_count()) as pool:
        pool.map(from_webp, jobs)
    return len(jobs)


def has_vulkan_loader():
    try:
        out = subprocess.run(["ldconfig", "-p"], capture_output=True, text=True).stdout
    except OSError:
        return False
    return all(lib in out for lib in LOADER_LIBS)


class Run:
    def __init__(self, a):
        self.a = a
        self.t0 = time.time()
        self.out = Path(a.out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.log = open(self.out / "log.txt", "a", buffering=1)
        self.results = {"small": a.small, "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
        self.work = Path(tempfile.mkdtemp(prefix="gpu_bench_"))
        self.bin = self.work / "stegongp"

    def note(self, msg):
        line = f"[{time.time() - self.t0:6.1f} s] {msg}"
        print(line, file=sys.stderr, flush=True)
        self.log.write(line + "\n")

    def save(self):
        self.results["wall_seconds"] = round(time.time() - self.t0, 1)
        tmp = self.out / "gpu_bench.json.tmp"
        tmp.write_text(json.dumps(self.results, indent=1))
        os.replace(tmp, self.out / "gpu_bench.json")

    def cmd(self, *args, json_out=False):
        """Runs the binary; its stderr goes to the log; stdout is returned (parsed as JSON if
        asked). A failure ends the run, its stderr saved in the JSON."""
        argv = [str(self.bin), *map(str, args)]
        self.note("+ stegongp " + " ".join(map(str, args)))
        t = time.time()
        p = subprocess.run(argv, capture_output=True, text=True)
        self.log.write(p.stderr)
        if p.returncode != 0:
            sys.stderr.write(p.stderr[-4000:])
            self.results.setdefault("errors", []).append(
                {"command": " ".join(map(str, args)), "stderr": p.stderr[-2000:]})
            self.save()
            fail(f"stegongp {args[0]} exited with {p.returncode}")
        self.note(f"  done in {time.time() - t:.1f} s")
        return json.loads(p.stdout) if json_out else p.stdout

    def setup(self):
        """The loader and the binary: enough to ask for the adapter."""
        d = Path(self.a.dir)
        debs = sorted((d / "gl").glob("*.deb")) if (d / "gl").is_dir() else []
        if debs and not has_vulkan_loader():
            for deb in debs:
                subprocess.run(["dpkg", "-x", str(deb), "/"], check=True)
            subprocess.run(["ldconfig"], check=True)
            self.note(f"installed the Vulkan loader from {len(debs)} .deb")
        if NVIDIA_ICD.is_file() and "VK_DRIVER_FILES" not in os.environ:
            os.environ["VK_DRIVER_FILES"] = str(NVIDIA_ICD)
            self.note(f"VK_DRIVER_FILES={NVIDIA_ICD}")
        with lzma.open(d / "stegongp.xz") as f:
            self.bin.write_bytes(f.read())
        self.bin.chmod(0o755)
        self.results["manifest"] = json.loads((d / "manifest.json").read_text())

    def data(self):
        """lego's images expanded, and the hidden text scene generated meanwhile: both cost
        CPU cores only, and both are done before anything is timed."""
        d = Path(self.a.dir)
        res, n_train = (32, 12) if self.a.small else (800, 100)
        synth = subprocess.Popen(
            [str(self.bin), "synth", "--scene", "text", "--res", str(res), "--train",
             str(n_train), "--test", "8", "--out", str(self.work / "text")],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        n = expand_scene(d / "lego", self.work / "lego")
        err = synth.communicate()[1]
        if synth.returncode != 0:
            self.log.write(err)
            fail("synth of the text scene failed: " + err[-500:])
        self.note(f"expanded {n} images; generated the text scene")

    def run(self):
        a = self.a
        small = a.small
        need_pillow()
        self.setup()
        devices = ["devices", "--json"] + ([] if a.allow_software else ["--require-hardware"])
        self.results["devices"] = self.cmd(*devices, json_out=True)
        opened = self.results["devices"]["opened"]
        if opened:
            self.note("adapter: " + opened["adapter"])
            self.note(f"  fma fused: {opened.get('fma_fused')}")
            for k, v in opened["limits"].items():
                self.note(f"  {k}: {v}")
        if "capture" in self.results["manifest"]:
            self.capture(opened)
            return
        self.data()
        self.save()

        lego = self.work / "lego"
        common = self.train_options()
        # Checkpoints score 8 test views (all the carried ones).
        scored = [*common, "--eval-views", "8"]
        lm = a.lego_minutes
        marks = [round(lm * (i + 1) / 5, 4) for i in range(5)]
        # One step in 50 timed phase by phase on the device (one extra read-back each).
        self.results["lego"] = self.cmd(
            "train", lego, "--out", self.work / "lego.ingp", "--minutes", lm,
            "--checkpoints", ",".join(map(str, marks)), "--profile-every",
            "5" if small else "50", *scored, json_out=True)
        self.results["lego"]["steady"] = steady(self.results["lego"])
        self.save()
        if a.lego_only:
            shutil.rmtree(self.work, ignore_errors=True)
            print(json.dumps(lego_summary(self.results, opened), indent=1))
            return

        text = self.work / "text"
        key = self.work / "keys" / "text.key"
        key.parent.mkdir(mode=0o700)
        self.cmd("keygen", "--out", key)
        pm = a.pair_minutes
        pair = self.cmd(
            "train", lego, "--hidden", text, "--key", key, "--out", self.work / "pair.ingp",
            "--minutes", pm, "--checkpoints", pm, *scored, json_out=True)
        self.results["pair"] = pair
        # A key holder's eval rebuilds the occupancy grid under the key: a second on a GPU,
        # a minute on llvmpipe, so the small run (CI) evaluates on the CPU engine.
        ev = ["--device", "cpu" if small else "gpu", "--json", "--no-lpips"]
        self.results["pair_hidden_key"] = self.cmd(
            "eval", "--model", self.work / "pair.ingp", "--data", text, "--key", key, *ev,
            json_out=True)
        self.results["pair_hidden_wrong_key"] = self.cmd(
            "eval", "--model", self.work / "pair.ingp", "--data", text, "--key", key,
            "--key-variant", "wrong", *ev, json_out=True)
        self.save()

        self.results["plain_text"] = self.cmd(
            "train", text, "--out", self.work / "text.ingp", "--steps", pair["steps"],
            *common, json_out=True)
        self.results["plain_text_eval"] = self.cmd(
            "eval", "--model", self.work / "text.ingp", "--data", text, *ev, json_out=True)
        # The hidden scene renders through a grid rebuilt from the network (its trained grid
        # is never stored); the plain model through the same kind of grid tells what sharing
        # the table costs apart from what the rebuilt grid costs.
        self.results["plain_text_rebuilt_eval"] = self.cmd(
            "eval", "--model", self.work / "text.ingp", "--data", text, "--rebuild-grid", *ev,
            json_out=True)
        self.save()
        self.results["summary"] = summary(self.results, opened)
        self.save()
        shutil.rmtree(self.work, ignore_errors=True)
        print(json.dumps(self.results["summary"], indent=1))

    def train_options(self):
        """`train`'s options for every GPU training of a run; tiny batches in small mode."""
        opts = ["--device", "gpu", "--json"] + (["--half-grid"] if self.a.half_grid else [])
        if self.a.small:
            opts += ["--batch", "4096", "--occupancy-fraction", "0.0078125"]
        return opts

    def capture(self, opened):
        """The carried capture trained on the GPU with the default options, its held-out views
        scored at each minute, and the model brought back in parts."""
        a = self.a
        src = Path(a.dir) / "capture"
        model = self.work / "capture.ingp"
        common = self.train_options()
        cm = a.capture_minutes
        k = 2 if a.small else max(1, min(5, round(cm)))
        marks = [round(cm * (i + 1) / k, 4) for i in range(k)]
        # Every held-out view (a capture's every 8th) at each checkpoint.
        r = self.cmd(
            "train", src, "--downscale", a.capture_downscale, "--out", model, "--minutes", cm,
            "--checkpoints", ",".join(map(str, marks)), "--profile-every",
            "5" if a.small else "50", "--eval-views", "1000", *common, json_out=True)
        r["steady"] = steady(r)
        self.results["capture"] = r
        self.save()
        self.results["capture_model"] = self.send_back(model)
        self.results["summary"] = capture_summary(self.results, opened)
        self.save()
        shutil.rmtree(self.work, ignore_errors=True)
        print(json.dumps(self.results["summary"], indent=1))

    def send_back(self, model):
        """`model` into OUT as parts of at most PART bytes (a lent machine returns no file
        over 16 MiB), with what `join` checks them against."""
        size = model.stat().st_size
        n = -(-size // PART)
        info = {"bytes": size, "sha256": sha256_of(model), "parts": []}
        if n > MAX_PARTS:
            self.note(f"the model ({size} bytes) is too large to come back in {MAX_PARTS} parts; "
                      "not written to OUT")
            return info
        with open(model, "rb") as f:
            for i in range(n):
                name = f"capture.ingp.part{i}"
                tmp = self.out / (name + ".tmp")
                tmp.write_bytes(f.read(PART))
                os.replace(tmp, self.out / name)
                info["parts"].append(name)
        self.note(f"model: {size} bytes in {n} parts under {self.out}")
        return info


def join(a):
    """The parts a capture run wrote, put together again and checked against its JSON."""
    res = Path(a.results)
    try:
        info = json.loads((res / "gpu_bench.json").read_text())["capture_model"]
    except (OSError, ValueError, KeyError) as e:
        fail(f"{res / 'gpu_bench.json'}: no capture model recorded ({e})")
    if not info["parts"]:
        fail(f"{res}: the run brought no parts back (the model was {info['bytes']} bytes)")
    out = Path(a.model)
    tmp = out.with_name(out.name + ".tmp")
    try:
        with open(tmp, "wb") as w:
            for name in info["parts"]:
                part = res / name
                if not part.is_file():
                    fail(f"{part}: missing")
                w.write(part.read_bytes())
        if tmp.stat().st_size != info["bytes"] or sha256_of(tmp) != info["sha256"]:
            fail(f"{res}: the parts do not make the model the run wrote "
                 f"({tmp.stat().st_size} bytes against {info['bytes']}, or another sha256)")
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    print(f"{out}: {info['bytes']} bytes, sha256 {info['sha256']}", file=sys.stderr)


def steady(train):
    """Trained samples/s and steps/s between the last two checkpoints: past the warm-up."""
    cps = train.get("checkpoints", [])
    if len(cps) < 2:
        return None
    a, b = cps[-2], cps[-1]
    dt = b["train_seconds"] - a["train_seconds"]
    if dt <= 0:
        return None
    return {
        "from_minutes": a["minutes"],
        "to_minutes": b["minutes"],
        "samples_per_second": (b["samples"] - a["samples"]) / dt,
        "marched_per_second": (b["marched"] - a["marched"]) / dt,
        "steps_per_second": (b["step"] - a["step"]) / dt,
    }


PER_STEP = ("trained_per_step", "marched_per_step", "network_per_step", "dropped_rays",
            "host_waits_per_step", "submissions_per_step")


def per_step(train, extra=()):
    """A training's counters per step (the keys of `train --json`)."""
    return {k: train.get(k) for k in (*PER_STEP, *extra)}


def device_ms(train):
    """A training's device time per step by phase, in ms."""
    return {p["phase"]: round(p["ms"], 3) for p in train.get("device_phases_ms", [])}


def lego_summary(r, opened):
    lego = r["lego"]
    return {
        "adapter": opened["adapter"] if opened else None,
        "lego_psnr_by_minute": {str(c["minutes"]): round(c["psnr"], 2) for c in lego["checkpoints"]},
        "lego_lpips_by_minute": {str(c["minutes"]): None if c.get("lpips") is None else round(c["lpips"], 4)
                                 for c in lego["checkpoints"]},
        "lego_steps": lego["steps"],
        "half_grid": lego.get("half_grid"),
        "lego_samples_per_second": round(lego["samples_per_second"]),
        "lego_steady": lego.get("steady"),
        "lego_per_step": per_step(lego),
        "lego_device_ms_per_step": device_ms(lego),
    }


def capture_summary(r, opened):
    c = r["capture"]
    return {
        "adapter": opened["adapter"] if opened else None,
        "capture": r["manifest"]["capture"]["source"],
        "capture_psnr_by_minute": {str(p["minutes"]): round(p["psnr"], 2) for p in c["checkpoints"]},
        "capture_steps": c["steps"],
        "capture_samples_per_second": round(c["samples_per_second"]),
        "capture_steady": c.get("steady"),
        "capture_per_step": per_step(c, ("occupancy_updates",)),
        "capture_device_ms_per_step": device_ms(c),
        "capture_model": r["capture_model"],
    }


def summary(r, opened):
    pair = r["pair"]
    s = {
        **lego_summary(r, opened),
        "pair_steps": pair["steps"],
        "pair_cover_psnr": round(pair["checkpoints"][-1]["psnr"], 2) if pair["checkpoints"] else None,
        "pair_hidden_psnr_key": round(r["pair_hidden_key"]["psnr"], 2),
        "pair_hidden_psnr_wrong_key": round(r["pair_hidden_wrong_key"]["psnr"], 2),
        "plain_text_psnr_same_steps": round(r["plain_text_eval"]["psnr"], 2),
        "plain_text_psnr_rebuilt_grid": round(r["plain_text_rebuilt_eval"]["psnr"], 2),
        "plain_text_seconds": round(r["plain_text"]["train_seconds"], 1),
    }
    return s


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="what", required=True)
    pp = sub.add_parser("prepare", help="build and pack what the other machine needs")
    pp.add_argument("dir")
    pp.add_argument("--lego", default=str(REPO.parent / "shared" / "data" / "lego"))
    pp.add_argument("--test-views", type=int, default=8)
    pp.add_argument("--binary", help="carry this binary instead of building the portable one")
    pp.add_argument("--no-loader", action="store_true", help="do not download the Vulkan loader")
    pp.add_argument("--small", action="store_true", help="fast compression (CI)")
    pp.add_argument("--force", action="store_true")
    pp.add_argument("--capture", help="carry this capture (any folder `train` reads) instead of lego")
    pp.add_argument("--capture-skip", action="append", default=[], metavar="REL",
                    help="leave out this file or folder of the capture (e.g. sparse_txt, a text "
                         "copy of its binary COLMAP model); repeatable")
    pr = sub.add_parser("run", help="measure, on the machine with the GPU")
    pr.add_argument("dir")
    pr.add_argument("out")
    pr.add_argument("--small", action="store_true", help="tiny sizes (CI, llvmpipe)")
    pr.add_argument("--allow-software", action="store_true",
                    help="accept a software adapter (llvmpipe): the CI test only")
    pr.add_argument("--lego-minutes", type=float, default=None)
    pr.add_argument("--pair-minutes", type=float, default=None)
    pr.add_argument("--lego-only", action="store_true",
                    help="lego alone (a second, shorter run on the same machine)")
    pr.add_argument("--half-grid", action="store_true",
                    help="train with the grid's fp16 copy (train --half-grid), to set beside a run without")
    pr.add_argument("--capture-minutes", type=float, default=None,
                    help="a carried capture's training budget (default 3)")
    pr.add_argument("--capture-downscale", type=int, default=None,
                    help="a carried capture's image downscale (default 4)")
    pj = sub.add_parser("join", help="here: the model a capture run brought back, in one file")
    pj.add_argument("results", help="the run's OUT, as it came back")
    pj.add_argument("model", help="the model file to write")
    a = p.parse_args()
    if a.what == "prepare":
        prepare(a)
    elif a.what == "join":
        join(a)
    else:
        if a.lego_minutes is None:
            a.lego_minutes = 0.05 if a.small else 5.0
        if a.pair_minutes is None:
            a.pair_minutes = 0.05 if a.small else 2.0
        if a.capture_minutes is None:
            a.capture_minutes = 0.05 if a.small else 3.0
        if a.capture_downscale is None:
            a.capture_downscale = 1 if a.small else 4
        Run(a).run()


if __name__ == "__main__":
    main()
