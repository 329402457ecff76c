#!/usr/bin/env python3
"""The viewer's frame time: starts `stegongp view MODEL` on a free port, then times frames at
its interactive size (a quarter of each side, `fast=1`) and at its full size, at the start
camera (the orbit's first view). Prints the medians of 5 requests after one warm-up: the
server's render time (its X-Render-Seconds header) and the whole request.

    python3 scripts/viewer_bench.py MODEL [--width 400 --height 400 ...view options]

STEGONGP names the program (default target/release/stegongp).
"""
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    model, extra = sys.argv[1], sys.argv[2:]
    if '--width' not in extra:
        extra += ['--width', '400', '--height', '400']
    exe = os.environ.get('STEGONGP', 'target/release/stegongp')
    record = os.path.join(tempfile.mkdtemp(), 'camera_path.json')  # never written: no button
    view = subprocess.Popen([exe, 'view', model, '--port', '0', '--record', record] + extra,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        url = view.stdout.readline().split()[1]
        base, token = url.split('/?token=')
        info = json.load(urllib.request.urlopen(f'{base}/info?token={token}'))
        c2w = ','.join(f'{x:.9g}' for x in info['start']['c2w'])
        fov = info['start']['fov']
        w, h, s = info['width'], info['height'], info['interactive_scale']
        for name, (fw, fh, fast) in {
            f'interactive {round(w * s)}x{round(h * s)}': (round(w * s), round(h * s), 1),
            f'full {w}x{h}': (w, h, 0),
        }.items():
            render, request = [], []
            for _ in range(6):
                t0 = time.time()
                r = urllib.request.urlopen(
                    f'{base}/frame?token={token}&c2w={c2w}&fov={fov}&w={fw}&h={fh}&fast={fast}')
                r.read()
                request.append(time.time() - t0)
                render.append(float(r.headers['X-Render-Seconds']))
            print(f'{name}: render {statistics.median(render[1:]):.3f} s, '
                  f'request {statistics.median(request[1:]):.3f} s (median of 5 after a warm-up)')
    finally:
        view.kill()


if __name__ == '__main__':
    main()
