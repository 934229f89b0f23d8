"""``needletrack dataset check|show|strip-truth``: validate a dataset folder against the spec and
its ground truth, look at it (a contact sheet with the true keypoints), and copy it without its
ground truth (what a user's recording holds)."""
from __future__ import annotations

import sys

from common.frames import CAMERAS


def add_parsers(sub) -> dict:
    """The ``check`` and ``show`` subcommands of ``needletrack dataset``; returns their handlers."""
    c = sub.add_parser("check", help="validate a folder against the dataset spec and its ground truth")
    c.add_argument("path")
    c.add_argument("--tol-px", type=float, default=0.1, help="max keypoint reprojection error (px)")
    c.add_argument("--no-images", action="store_true", help="skip decoding every image")

    s = sub.add_parser("show", help="contact sheet of frames with the ground-truth keypoints")
    s.add_argument("path")
    s.add_argument("--out", required=True, help="output PNG")
    s.add_argument("--frames", type=int, default=12, help="number of frames (evenly spaced)")
    s.add_argument("--cols", type=int, default=4)
    s.add_argument("--camera", default="left", choices=list(CAMERAS))
    s.add_argument("--tile-width", type=int, default=480)

    t = sub.add_parser("strip-truth", help="copy a folder without its ground truth (needle pose, "
                                           "keypoints, visible, bbox): the images, calibration and "
                                           "endoscope poses a recording holds")
    t.add_argument("path")
    t.add_argument("--out", required=True, help="output folder (new; images hard-linked when possible)")
    return {"check": _check, "show": _show, "strip-truth": _strip}


def _strip(args) -> int:
    from common.data.writer import without_truth
    n = without_truth(args.path, args.out)
    print(f"{args.out}: {n} frames without ground truth")
    return 0


def _check(args) -> int:
    from common.data.check import check_dataset
    from common.data.dataset import Dataset
    ds = Dataset(args.path)
    rep = check_dataset(ds, tol_px=args.tol_px, images=not args.no_images, progress=sys.stderr.isatty())
    print(f"{args.path}: {rep.frames} frames, {ds.meta.image_size[0]}x{ds.meta.image_size[1]}, "
          f"{len(ds.sequences())} sequences; ground truth in {rep.with_truth} frames")
    if rep.with_truth:
        print(f"  keypoint reprojection: max {rep.max_reproj_px:.2e} px, mean {rep.mean_reproj_px:.2e} px "
              f"(tolerance {args.tol_px} px)")
    if ds.arm is not None:
        print(f"  ECM forward kinematics vs T_world_ecm: max {rep.max_fk_m:.2e} m")
    if not args.no_images:
        print(f"  images decoded: {rep.images_checked}")
    for w in rep.warnings:
        print(f"  warning: {w}")
    for e in rep.errors:
        print(f"  error: {e}")
    print("OK" if rep.ok else f"FAILED ({len(rep.errors)} errors)")
    return 0 if rep.ok else 1


def _show(args) -> int:
    import cv2

    from common.data.dataset import Dataset
    ds = Dataset(args.path)
    sheet = contact_sheet(ds, n=args.frames, cols=args.cols, camera=args.camera, tile_width=args.tile_width)
    if not cv2.imwrite(args.out, sheet):
        raise OSError(f"could not write {args.out}")
    print(f"{args.out}: {sheet.shape[1]}x{sheet.shape[0]} contact sheet of {min(args.frames, len(ds))} frames")
    return 0


# ---------------------------------------------------------------- contact sheet

# A..E: red, orange, yellow, green, blue (BGR)
KEYPOINT_COLOURS = ((40, 40, 230), (0, 150, 255), (0, 230, 230), (60, 200, 60), (230, 120, 30))


def draw_keypoints(img, uv, visible, scale: float = 1.0, offset=(0.0, 0.0), radius: int = 4):
    """Draw A..E on ``img`` in place: filled discs where visible, rings where not."""
    import cv2
    import numpy as np
    for k in range(5):
        p = (np.asarray(uv[k], float) - offset) * scale
        if not np.all(np.isfinite(p)):
            continue
        c = (int(round(p[0] * 16)), int(round(p[1] * 16)))
        if visible is None or bool(visible[k]):
            cv2.circle(img, c, radius * 16, (0, 0, 0), -1, cv2.LINE_AA, shift=4)
            cv2.circle(img, c, (radius - 1) * 16, KEYPOINT_COLOURS[k], -1, cv2.LINE_AA, shift=4)
        else:
            cv2.circle(img, c, (radius + 2) * 16, (0, 0, 0), 3, cv2.LINE_AA, shift=4)
            cv2.circle(img, c, (radius + 2) * 16, KEYPOINT_COLOURS[k], 1, cv2.LINE_AA, shift=4)


def contact_sheet(ds, n: int = 12, cols: int = 4, camera: str = "left", tile_width: int = 480):
    """BGR contact sheet of ``n`` evenly spaced frames: ground-truth keypoints A..E (filled =
    visible, ring = occluded or outside), the needle's box, and a zoomed inset of the needle."""
    import cv2
    import numpy as np
    n = max(1, min(n, len(ds)))
    idx = np.unique(np.linspace(0, len(ds) - 1, n).round().astype(int))
    w, h = ds.meta.image_size
    s = tile_width / w
    th = int(round(h * s))
    tiles = []
    for i in idx:
        fr = ds[int(i)]
        img = ds.image(fr, camera)
        tile = cv2.resize(img, (tile_width, th), interpolation=cv2.INTER_AREA)
        uv = None if fr.keypoints is None else fr.keypoints[camera]
        vis = None if fr.visible is None else fr.visible[camera]
        box = None if fr.bbox is None else fr.bbox.get(camera)
        if box is not None:
            cv2.rectangle(tile, (int(box[0] * s), int(box[1] * s)), (int(box[2] * s), int(box[3] * s)),
                          (255, 255, 255), 1)
        if uv is not None:
            # inset: the needle region magnified, in the top-right corner
            lo, hi = uv.min(axis=0), uv.max(axis=0)
            half = max(float(np.max(hi - lo)) * 0.8, 20.0)
            cx, cy = (lo + hi) / 2
            x0, y0 = int(max(0, cx - half)), int(max(0, cy - half))
            x1, y1 = int(min(w, cx + half)), int(min(h, cy + half))
            if x1 - x0 > 4 and y1 - y0 > 4:
                isz = int(tile_width * 0.4)
                z = isz / max(x1 - x0, y1 - y0)
                crop = cv2.resize(img[y0:y1, x0:x1], (int((x1 - x0) * z), int((y1 - y0) * z)),
                                  interpolation=cv2.INTER_CUBIC)
                draw_keypoints(crop, uv, vis, z, (x0, y0), radius=max(3, int(isz / 40)))
                ch, cw = crop.shape[:2]
                tile[2:2 + ch, tile_width - cw - 2:tile_width - 2] = crop
                cv2.rectangle(tile, (tile_width - cw - 3, 1), (tile_width - 2, ch + 2), (255, 255, 255), 1)
            draw_keypoints(tile, uv, vis, s, radius=3)
        label = f"#{fr.index}"
        if fr.sequence is not None:
            label += f" seq {fr.sequence} step {fr.step}"
        cv2.putText(tile, label, (6, th - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(tile, label, (6, th - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    cols = max(1, min(cols, len(tiles)))
    rows = (len(tiles) + cols - 1) // cols
    sheet = np.full((28 + rows * (th + 4), cols * (tile_width + 4), 3), 32, np.uint8)
    x = 8
    for k, name in enumerate("ABCDE"):
        cv2.circle(sheet, (x + 6, 14), 6, KEYPOINT_COLOURS[k], -1, cv2.LINE_AA)
        cv2.putText(sheet, name + (" (tip)" if k == 0 else " (tail)" if k == 4 else ""), (x + 16, 19),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.5, (230, 230, 230), 1, cv2.LINE_AA)
        x += 90 if k in (0, 4) else 50
    cv2.putText(sheet, f"{camera} camera; filled = visible, ring = occluded/outside", (x + 10, 19),
                cv2.FONT_HERSHEY_SIMPLEX, 0.45, (200, 200, 200), 1, cv2.LINE_AA)
    for t, tile in enumerate(tiles):
        r, c = divmod(t, cols)
        y0, x0 = 28 + r * (th + 4), c * (tile_width + 4)
        sheet[y0:y0 + th, x0:x0 + tile_width] = tile
    return sheet

