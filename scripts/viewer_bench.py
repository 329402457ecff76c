#!/usr/bin/env python3
"""The viewer's frame time: starts `stegongp view MODEL` on a free port, then times frames at
its interactive size (a quarter of each side, `fast=1`) and at its full size, at the start
camera (the orbit's first view). Prints the medians of 5 requests after one warm-up: the
server's render time (its X-Render-Seconds header) and the whole request.

With `--moving N` (first), it then plays N moving frames as the page does while the camera
moves: each frame's side scaled by the page's dynamic-resolution rule (viewer.html's
`V.adapt`: x sqrt(aim / last render seconds), at most x2 or x1/2 a frame, between 1/16 of the
full size and the interactive scale), and prints each frame's size and render seconds.

    python3 scripts/viewer_bench.py [--moving N] MODEL [--width 400 --height 400 ...view options]

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
    args = sys.argv[1:]
    moving = 0
    if args[:1] == ['--moving']:
        moving, args = int(args[1]), args[2:]
    if not args:
        sys.exit(__doc__)
    model, extra = args[0], args[1:]
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
        frame = lambda fw, fh: float(urllib.request.urlopen(
            f'{base}/frame?token={token}&c2w={c2w}&fov={fov}&w={fw}&h={fh}&fast=1'
        ).headers['X-Render-Seconds'])
        aim, scale = info['frame_seconds'], s
        for i in range(moving):
            fw, fh = max(1, round(w * scale)), max(1, round(h * scale))
            seconds = frame(fw, fh)
            print(f'moving frame {i + 1}: {fw}x{fh} in {seconds:.3f} s (aim {aim} s)')
            if aim > 0 and seconds > 0:
                f = min(2.0, max(0.5, (aim / seconds) ** 0.5))
                scale = min(s, max(min(s, 1 / 16), scale * f))
    finally:
        view.kill()


if __name__ == '__main__':
    main()
