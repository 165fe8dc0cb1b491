"""``rtctl render IMAGE``: per-pin parameters at one HIA position (or along a path: a raster scan,
way-points or a mouse recording) and the intermediate images.

``main(argv) -> int`` raises :class:`rtctl.errors.RtctlError` subclasses for bad input (the
``rtctl`` wrapper prints them as one line and exits 2); run as ``python -m rtctl.render.cli``
it does the same itself.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys

from rtctl.errors import RtctlError, SceneError

__all__ = ["main", "parser"]

_DEFAULTS = {  # grid, hia (px) per method: the seeds' displays
    "roi": ((4, 4), 32), "canny": ((4, 4), 32), "frequency": ((3, 3), 33), "beat": ((6, 8), 96),
}


def _pair(text, sep, kind, what):
    try:
        a, b = (kind(v) for v in text.lower().split(sep))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what} {text!r} must look like A{sep}B") from None
    return a, b


def _in_scene_range(flag: str, value, key: str, scale: float = 1.0):
    """``value`` of ``flag``, held to the range of the scene key ``stimulus.KEY`` it stands for
    (given in that key's unit, ``value * scale``): the same bounds as a scene's, and no NaN or
    infinity reaching the renderer's pixel arithmetic."""
    from rtctl.schema import SCENE

    k = SCENE.keys["stimulus"].keys[key]
    v = value * scale
    if not (math.isfinite(v) and (v > k.lo if k.open_lo else v >= k.lo) and v <= k.hi):
        raise SceneError(f"{flag} {value!r}: out of range; stimulus.{key} allows {k.describe_range()} {k.unit}")
    return value


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="rtctl render", description="Render an image to per-pin stimulus parameters.")
    p.add_argument("image", metavar="IMAGE", help="image file (PNG, JPEG, ...; 8-bit gray or colour)")
    p.add_argument("--method", choices=tuple(_DEFAULTS), default="frequency",
                   help="roi | canny (binary pins, seed 001), frequency (seed 003; the default), beat (seed 004)")
    p.add_argument("--grid", type=lambda s: _pair(s, "x", int, "--grid"), metavar="RxC",
                   help="pins rows x cols (default: 4x4 roi/canny, 3x3 frequency, 6x8 beat)")
    p.add_argument("--hia", type=int, metavar="PX", help="HIA side in pixels (default 32, 33, 96)")
    p.add_argument("--at", type=lambda s: _pair(s, ",", float, "--at"), metavar="X,Y",
                   help="HIA centre in pixels, x right, y down (default: image centre)")
    p.add_argument("--mm-per-px", type=float, metavar="S",
                   help="pixel size on the display, mm (beat; default pitch 1.5 mm / px per pin)")
    p.add_argument("--normalize", choices=("field", "image"),
                   help="beat: valid-blob count over the physiological maximum, the HIA area over the 12.6 mm^2 "
                        "receptive field (field, default), or over the image's densest HIA window (image)")
    p.add_argument("--path", metavar="PATH",
                   help="render along a path instead of --at: 'raster' (a serpentine scan at --speed, lines one HIA "
                        "apart), way-points 'X,Y;X,Y;...' (px, at --speed) or 'X,Y@T;X,Y@T;...' (T in s), or a CSV "
                        "file (a mouse recording t,x,y; or way-points under a header x,y, at --speed)")
    p.add_argument("--speed", type=float, default=200.0, metavar="PX/S",
                   help="HIA speed along a raster or untimed way-points (default 200)")
    p.add_argument("--rate", type=float, default=1000.0, metavar="HZ", help="render rate along --path (default 1000)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--out", metavar="DIR", help="write the intermediate images (and params.npy for --path) here")
    return p


def main(argv=None) -> int:
    """Run ``rtctl render``; returns 0, raises :class:`RtctlError` on bad input."""
    args = parser().parse_args(argv)
    for x in args.at or ():
        _in_scene_range("--at", x, "at")
    _in_scene_range("--speed", args.speed, "speed")
    _in_scene_range("--rate", args.rate, "rate")
    if args.hia is not None:
        _in_scene_range("--hia", args.hia, "hia")
    if args.mm_per_px is not None:
        _in_scene_range("--mm-per-px", args.mm_per_px, "px_size", 1e-3)
    from rtctl.render.factory import make_renderer
    from rtctl.render.image import load_image

    image = load_image(args.image)
    if args.out is not None:  # an empty --out is refused there, not skipped
        from rtctl.outpath import writable_dir

        writable_dir(args.out, "--out")
    grid, hia = _DEFAULTS[args.method]
    kw = {"grid": args.grid or grid, "hia": args.hia if args.hia is not None else hia}
    if args.mm_per_px is not None:
        if args.method != "beat":
            raise SceneError(f"--mm-per-px applies to --method beat only (got --method {args.method})")
        kw["px_size"] = args.mm_per_px * 1e-3
    if args.normalize is not None:
        if args.method != "beat":
            raise SceneError(f"--normalize applies to --method beat only (got --method {args.method})")
        kw["normalize"] = args.normalize
    r = make_renderer(args.method, **kw).prepare(image)
    H, W = r.image_shape
    x, y = args.at if args.at is not None else ((W - 1) / 2.0, (H - 1) / 2.0)
    out = r.empty()
    status = r.update(x, y, out)
    res = {"image": os.fspath(args.image), "method": r.method, "grid": list(r.grid), "hia_px": r.hia,
           "cell_px": r.cell, "image_px": [W, H], "at": [x, y], "status": status}
    if args.method == "beat":
        res.update(mm_per_px=r.px_size * 1e3, normalize=r.normalize, max_count=list(r.max_count),
                   valid_blobs=int(r.valid.sum()), blobs=int(r.valid.size - 1))
    res["pins"] = r.pins(out)
    frames = None
    if args.path is not None:
        from rtctl.render.path import parse_path

        path = parse_path(args.path, W, H, speed=args.speed, rate=args.rate, step=float(r.shape[0]))
        frames = r.render_path(path.x, path.y)
        res["path"] = {"spec": args.path, "updates": len(path), "rate_hz": path.rate,
                       "duration_s": float(path.t[-1] - path.t[0]),
                       "start": [float(path.x[0]), float(path.y[0])], "end": [float(path.x[-1]), float(path.y[-1])]}
    if args.out is not None:
        res["files"] = _write(args.out, r, image, x, y, out, frames)
    if args.json:
        print(json.dumps(res))
    else:
        _table(res, r.fields)
    return 0


def _write(d, r, image, x, y, out, frames):
    import cv2
    import numpy as np

    os.makedirs(d, exist_ok=True)
    files = []
    for name, img in r.images().items():
        f = os.path.join(d, f"{name}.png")
        cv2.imwrite(f, img)
        files.append(f)
    f = os.path.join(d, "hia.png")
    cv2.imwrite(f, draw_hia(image, r, x, y, out))
    files.append(f)
    if frames is not None:
        f = os.path.join(d, "params.npy")
        np.save(f, frames)
        files.append(f)
    return files


def draw_hia(image, r, x, y, out):
    """BGR copy of ``image`` with the HIA's cells (green) and a dot per pin whose brightness is
    its value (up, or frequency / the method's maximum); uint8, shape (H, W, 3)."""
    import cv2

    from rtctl.render.hia import FIELDS

    img = image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    img = img.copy()
    k = FIELDS.index(r.fields[0])
    vals = out[:, k]
    top = vals.max() if vals.max() > 0 else 1.0
    thick = max(1, r.cell // 12)
    for p, (a, c, b, d) in enumerate(r.hia_rects(x, y)):
        cv2.rectangle(img, (c, a), (d - 1, b - 1), (0, 200, 0), thick)
        v = vals[p] / top
        centre = ((c + d - 1) // 2, (a + b - 1) // 2)
        cv2.circle(img, centre, max(1, r.cell // 3), (0, int(255 * v), int(255 * v)), -1)  # yellow = up/high
        cv2.circle(img, centre, max(1, r.cell // 3), (0, 0, 255), 1)
    return img


def _table(res, fields):
    print(f"{res['method']} {res['grid'][0]}x{res['grid'][1]} pins, HIA {res['hia_px']} px at "
          f"({res['at'][0]:g}, {res['at'][1]:g}) of a {res['image_px'][0]}x{res['image_px'][1]} px image")
    print("  ".join(["row", "col"] + [f"{f:>10}" for f in fields]))
    for p in res["pins"]:
        print("  ".join([f"{p['row']:>3}", f"{p['col']:>3}"] + [f"{p[f]!s:>10}" for f in fields]))
    for f in res.get("files", []):
        print("wrote", f)


if __name__ == "__main__":  # pragma: no cover - the rtctl wrapper does this for `rtctl render`
    try:
        sys.exit(main())
    except RtctlError as e:
        print(f"rtctl: error: {e}", file=sys.stderr)
        sys.exit(2)
