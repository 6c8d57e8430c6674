"""Everything a stylization run writes to its folder (besides config.yaml, log.jsonl and checkpoint.pt,
which the loop keeps current): stylized.ply (and, for web viewers, stylized.compressed.ply and stylized.spz),
cameras.json, sources.json (where the inputs came from), renders/ originals/ photos/, style.png, comparison.png,
orbit.mp4 (H.264), stroke_field.png, loss_curves.png and metrics.json. All writes are atomic."""
from __future__ import annotations

import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import torch

from ..fileio import atomic_path, write_image, write_json
from ..io import save_ply
from ..io.splat_formats import save_compressed_ply, save_spz
from ..renderer import render
from ..train.optim import quat_to_rotmat, rotmat_to_quat
from ..train.reconstruct import cameras_json
from ..types import Camera, Gaussians
from .pipeline import HOLE_ALPHA, LOG_TERMS

RANDOM_VGG_NOTE = "VGG-16 RANDOM (not pretrained): style/content losses are not meaningful"
ZOOM = 4  # the comparison's zoom column: the centre of the stylized view magnified this much (nearest)


def to_u8(img) -> np.ndarray:
    """An image in [0,1] (a tensor [H,W,C] on any device, or numpy) as uint8 numpy, NaN as 0, rounded."""
    if isinstance(img, torch.Tensor):  # on its device (the GPU for renders): 4x less to copy, no numpy pass
        return (img.detach().nan_to_num(0.0).clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()
    a = np.asarray(img)
    return a if a.dtype == np.uint8 else np.clip(np.nan_to_num(a) * 255.0 + 0.5, 0, 255).astype(np.uint8)


def _fit_painting(style: np.ndarray, h: int, w: int) -> np.ndarray:
    """The painting center-cropped to the view's aspect and resized to h x w."""
    sh, sw = style.shape[:2]
    if sw / sh > w / h:
        cw = max(1, round(sh * w / h))
        x0 = (sw - cw) // 2
        style = style[:, x0:x0 + cw]
    else:
        ch = max(1, round(sw * h / w))
        y0 = (sh - ch) // 2
        style = style[y0:y0 + ch]
    return cv2.resize(np.ascontiguousarray(style, np.float32), (w, h), interpolation=cv2.INTER_AREA)


def font_scale(panel_width: int, longest: str = "original render") -> float:
    """The label font scale for panels ``panel_width`` pixels wide: ``longest`` fits one panel (0.3 to 0.8)."""
    w1 = cv2.getTextSize(longest, cv2.FONT_HERSHEY_SIMPLEX, 1.0, 1)[0][0]
    return float(min(0.8, max(0.3, (panel_width - 8) / max(1, w1))))


def wrap_text(text: str, scale: float, width: int) -> list:
    """``text`` in lines no wider than ``width`` pixels at ``scale`` (Hershey simplex), broken between words only;
    a word wider than a line (a long path) is broken after a "/" (a word with none keeps a line of its own)."""
    def fits(t):
        return cv2.getTextSize(t, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0] <= width

    lines, cur = [], ""
    for word in text.split():
        trial = f"{cur} {word}" if cur else word
        if fits(trial):
            cur = trial
            continue
        if cur:
            lines.append(cur)
        cur = word
        while not fits(cur) and "/" in cur[:-1]:  # the longest head ending in "/" that fits (else the first)
            cuts = [i + 1 for i, ch in enumerate(cur[:-1]) if ch == "/"]
            cut = next((i for i in reversed(cuts) if fits(cur[:i])), cuts[0])
            lines.append(cur[:cut])
            cur = cur[cut:]
    return lines + [cur] if cur else lines or [""]


def _text_block(lines: list, width: int, scale: float, color, x_off: int = 0, canvas=None) -> np.ndarray:
    (_, th), base = cv2.getTextSize("Ag", cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    step = th + base + max(2, round(4 * scale))
    img = canvas if canvas is not None else np.full((step * len(lines) + 6, width, 3), 255, np.uint8)
    for i, line in enumerate(lines):
        cv2.putText(img, line, (x_off + 4, 3 + th + i * step), cv2.FONT_HERSHEY_SIMPLEX, scale, color, 1, cv2.LINE_AA)
    return img


def zoom_crop(img: np.ndarray, zoom: int = ZOOM) -> np.ndarray:
    """The centre 1/zoom of ``img`` (rows and columns) magnified zoom times with nearest neighbour: each pixel of
    the render becomes a zoom x zoom block, so the strokes are seen as they were rendered."""
    h, w = img.shape[:2]
    ch, cw = max(1, h // zoom), max(1, w // zoom)
    y0, x0 = (h - ch) // 2, (w - cw) // 2
    crop = img[y0:y0 + ch, x0:x0 + cw]
    big = np.repeat(np.repeat(crop, zoom, 0), zoom, 1)
    out = np.zeros_like(img)  # the panel keeps the view's size (a remainder of rows / columns stays black)
    out[:big.shape[0], :big.shape[1]] = big[:h, :w]
    return out


def comparison_caption(cfg, iterations: int, alignment: float) -> str:
    """What comparison.png was made with: the stylize controls that differ from neutral (strength 1, stroke scale 1,
    the palette), the settings that change a picture most, the terms that are on only."""
    lum = (f"luminance_only=True ({cfg.loss.luminance_grad} gradient)" if cfg.loss.luminance_only
           else "luminance_only=False") + f", content on {cfg.loss.content_on}"
    extra = (f", conv4 {cfg.loss.deep_loss} term x{cfg.loss.w_style_deep:g}" if cfg.loss.w_style_deep else "") + (
        f", tone hold x{cfg.loss.w_tone_hold:g} (margin {cfg.loss.tone_margin:g}"
        + (f", {cfg.loss.tone_cells} rows of cells)" if cfg.loss.tone_cells else ")") if cfg.loss.w_tone_hold else "")
    controls = ((f"strength {cfg.loss.strength:g}, " if cfg.loss.strength != 1 else "")
                + (f"stroke scale {cfg.stroke_scale:g}, " if cfg.stroke_scale != 1 else "")
                + ("keep colours, " if cfg.keep_colors else ""))
    palette = ("none" if cfg.keep_colors else cfg.palette_map
               + (f" (smoothed {cfg.palette_smooth:g}" + (f", focus {cfg.palette_focus:g}" if cfg.palette_focus else "")
                  + ")" if cfg.palette_map == "sliced" and cfg.palette_smooth else ""))
    jitter = f", {cfg.stroke_jitter_mode} jitter x{cfg.stroke_jitter:g}" if cfg.stroke_jitter else ""
    return (f"{controls}config: palette={palette}{jitter}, style={cfg.loss.style_loss}, {lum}{extra}, "
            f"lock_xyz={cfg.geometry.lock_xyz}, max_travel={cfg.geometry.max_travel:g}, "
            f"colour_floor={cfg.colour_floor}, w_align={cfg.loss.w_align}, field={cfg.loss.field_mapping}; "
            f"{iterations} iterations; alignment to its training field {alignment:.3f}")


def weights_name(source: str) -> str:
    """The VGG source as a picture caption shows it: the weights' file name, not the folder it sits in on this
    machine (metrics.json keeps the whole path)."""
    head, sep, path = source.rpartition(" from ")
    return f"{head}{sep}{Path(path).name}" if sep else Path(source).name


def comparison_grid(rows: list, painting: np.ndarray, caption: str) -> np.ndarray:
    """rows: [(photo, original, stylized)] float [H,W,3]; returns a uint8 RGB grid at the views' own resolution
    with a header and a caption: photo | original render | stylized | stylized, its centre magnified ZOOM times
    (nearest neighbour: the strokes pixel for pixel) | painting. Labels and caption are sized from the panel
    width and wrapped between words."""
    h, w = rows[0][0].shape[:2]
    paint = to_u8(_fit_painting(painting, h, w))
    zoom = ZOOM if min(h, w) >= 16 * ZOOM else 2
    body = np.concatenate([np.concatenate([to_u8(ph), to_u8(org), to_u8(sty), zoom_crop(to_u8(sty), zoom), paint], 1)
                           for ph, org, sty in rows], 0)
    W = body.shape[1]
    names = ("photo", "original render", "stylized", f"stylized, centre x{zoom}", "painting")
    scale = font_scale(w)
    wrapped = [wrap_text(n, scale, w - 8) for n in names]
    depth = max(len(x) for x in wrapped)
    head = _text_block([""] * depth, W, scale, (0, 0, 0))
    for j, lines in enumerate(wrapped):
        _text_block(lines, W, scale, (0, 0, 0), x_off=j * w, canvas=head)
    color = (200, 0, 0) if "RANDOM" in caption else (0, 0, 0)
    foot = _text_block(wrap_text(caption, scale, W - 8), W, scale, color)
    return np.concatenate([head, body, foot], 0)


# --- the orbit path ------------------------------------------------------------------------------------------
def slerp_rotations(R: np.ndarray, ts: np.ndarray) -> np.ndarray:
    """Rotations [K, 3, 3] keyed at t = 0..K-1, interpolated at ``ts`` [T] along the shortest arc between
    neighbours (what scipy's Slerp gives; scipy's package import took 0.6 s of a stylize run's start).
    Returns [T, 3, 3]."""
    q = rotmat_to_quat(R)  # [K, 4]
    i = np.clip(np.floor(ts).astype(int), 0, len(q) - 2)
    f = (ts - i)[:, None]
    q0, q1 = q[i], q[i + 1]
    dot = (q0 * q1).sum(1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)  # the shorter of the two arcs
    theta = np.arccos(np.clip(np.abs(dot), 0.0, 1.0))
    sin = np.sin(theta)
    small = sin < 1e-9  # (nearly) equal rotations: linear weights, normalized below
    w0 = np.where(small, 1 - f, np.sin((1 - f) * theta) / np.where(small, 1.0, sin))
    w1 = np.where(small, f, np.sin(f * theta) / np.where(small, 1.0, sin))
    return quat_to_rotmat(torch.from_numpy(w0 * q0 + w1 * q1)).numpy()


def orbit_path(cams: list, n_frames: int) -> list:
    """Cameras interpolated through the dataset cameras in order (positions linear, rotations slerp); a closed
    loop when the last camera is about one step from the first (an orbit), an open path otherwise.
    Intrinsics are the first camera's."""
    c2w = [torch.linalg.inv(c.world_to_camera.double()).numpy() for c in cams]
    pos = np.stack([m[:3, 3] for m in c2w])
    rots = [m[:3, :3] for m in c2w]
    if len(cams) == 1 or n_frames <= 1:
        return [cams[0]] * max(1, n_frames)
    steps = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    closed = len(cams) > 2 and np.linalg.norm(pos[-1] - pos[0]) < 2.0 * max(np.median(steps), 1e-12)
    if closed:
        pos = np.concatenate([pos, pos[:1]])
        rots = rots + rots[:1]
    key_t = np.arange(len(pos), dtype=np.float64)
    ts = np.linspace(0, key_t[-1], n_frames, endpoint=not closed)
    R_t = slerp_rotations(np.stack(rots), ts)
    out = []
    for t, R in zip(ts, R_t):
        i = min(int(t), len(pos) - 2)
        f = t - i
        p = (1 - f) * pos[i] + f * pos[i + 1]
        w2c = np.eye(4)
        w2c[:3, :3] = R.T
        w2c[:3, 3] = -R.T @ p
        c0 = cams[0]
        out.append(Camera(torch.from_numpy(w2c), c0.fx, c0.fy, c0.cx, c0.cy, c0.width, c0.height, c0.near, c0.far,
                          name=f"orbit_{len(out):04d}"))
    return out


VIDEO_CRF = 18  # x264 quality: visually lossless for these renders, ~1 MB for the demo's 96 frames


def _even(frame: np.ndarray) -> np.ndarray:
    """yuv420p needs even width and height: repeat the last row / column where one is odd."""
    h, w = frame.shape[:2]
    return np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


def write_video(path: Path, frames: list, fps: int) -> str | None:
    """mp4 in H.264 (libx264, yuv420p, moov atom first) with imageio-ffmpeg's bundled ffmpeg, so browsers
    play it. Without imageio-ffmpeg: OpenCV's mp4v, which browsers do not play; returns a note saying so
    (None when H.264 was written). Raises RuntimeError when no encoder works (the caller then writes PNGs)."""
    frames = [_even(to_u8(f)) for f in frames]
    h, w = frames[0].shape[:2]
    try:
        import imageio_ffmpeg  # lazy: optional (without it, OpenCV's mp4v below)
    except ImportError:
        _write_video_mp4v(path, frames, fps, w, h)
        return "orbit.mp4 is MPEG-4 Part 2 (mp4v; browsers do not play it): pip install imageio-ffmpeg for H.264"
    with atomic_path(path) as tmp:
        writer = imageio_ffmpeg.write_frames(str(tmp), (w, h), fps=float(fps), codec="libx264", pix_fmt_in="rgb24",
                                             pix_fmt_out="yuv420p", macro_block_size=1, quality=None,
                                             output_params=["-crf", str(VIDEO_CRF), "-movflags", "+faststart"])
        try:
            writer.send(None)  # start ffmpeg
            for f in frames:
                writer.send(np.ascontiguousarray(f))
        except (RuntimeError, BrokenPipeError) as e:
            raise RuntimeError(f"ffmpeg failed: {e}") from None
        finally:
            writer.close()
        if not tmp.exists() or tmp.stat().st_size == 0:
            raise RuntimeError("ffmpeg produced no file")
    return None


def _write_video_mp4v(path: Path, frames: list, fps: int, w: int, h: int) -> None:
    with atomic_path(path) as tmp:
        vw = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
        if not vw.isOpened():
            vw.release()
            raise RuntimeError("mp4v codec unavailable")
        for f in frames:
            vw.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
        vw.release()
        if not tmp.exists() or tmp.stat().st_size == 0:
            raise RuntimeError("mp4v writer produced no file")


def curve(log: list, term: str) -> tuple:
    """(steps, values) of one log column, over the rows that have it (a loss term: where it is not 0), with a NaN
    between two points of different phases: the plotted line breaks at each phase boundary instead of joining,
    say, the end of the pre-process to the start of the post-process across the stylize phase."""
    xs, ys, last = [], [], None
    for r in log:
        if term not in r or (term != "flow_score" and r.get(term, 0) == 0):
            continue
        if last is not None and r.get("phase") != last:
            xs.append(r["step"] - 0.5)
            ys.append(float("nan"))
        xs.append(r["step"])
        ys.append(float(r[term]))
        last = r.get("phase")
    return np.asarray(xs, dtype=np.float64), np.asarray(ys, dtype=np.float64)


PANEL_W, PANEL_H, PLOT_MARGIN = 360, 200, (58, 10, 24, 22)  # a panel of loss_curves.png; margins left/right/top/bottom
CURVE_BGR, GRID_BGR, TEXT_BGR = (180, 100, 30), (160, 160, 160), (30, 30, 30)


def panel_points(x: np.ndarray, y: np.ndarray, box: tuple, log_y: bool) -> tuple:
    """Pixel positions of the finite points (x, y) in ``box`` = (x0, y0, x1, y1), the y range spanning the data
    (log10 of it when ``log_y``): ([K, 2] int32 pixel coordinates, the index of each point's run of finite
    points (a NaN in ``y`` starts a new run), (y_lo, y_hi) in data units)."""
    x0, y0, x1, y1 = box
    ok = np.isfinite(y)
    run = np.cumsum(~ok)[ok]  # NaN breaks the line
    v = np.log10(y[ok]) if log_y else y[ok]
    xs = x[ok]
    lo, hi = (float(v.min()), float(v.max())) if len(v) else (0.0, 1.0)
    if hi - lo < 1e-12:
        lo, hi = lo - 0.5, hi + 0.5
    xlo, xhi = (float(x.min()), float(x.max())) if len(x) else (0.0, 1.0)
    xhi = xhi if xhi > xlo else xlo + 1.0
    px = x0 + (xs - xlo) / (xhi - xlo) * (x1 - x0)
    py = y1 - (v - lo) / (hi - lo) * (y1 - y0)
    pts = np.stack([np.rint(px), np.rint(py)], -1).astype(np.int32)
    span = (10 ** lo, 10 ** hi) if log_y else (lo, hi)
    return pts, run, span


def _panel(log: list, term: str, bounds: list) -> np.ndarray:
    img = np.full((PANEL_H, PANEL_W, 3), 255, np.uint8)
    ml, mr, mt, mb = PLOT_MARGIN
    box = (ml, mt, PANEL_W - mr, PANEL_H - mb)
    x, y = curve(log, term)
    finite = y[np.isfinite(y)]
    log_y = term != "flow_score" and len(finite) > 0 and bool(np.all(finite > 0))
    cv2.rectangle(img, box[:2], box[2:], GRID_BGR, 1)
    font, small = cv2.FONT_HERSHEY_SIMPLEX, 0.36
    cv2.putText(img, term + (" (log)" if log_y else ""), (ml, 15), font, 0.45, TEXT_BGR, 1, cv2.LINE_AA)
    if len(finite):
        pts, run, (lo, hi) = panel_points(x, y, box, log_y)
        xlo, xhi = float(x.min()), float(x.max())
        for b in bounds:  # phase boundaries, dashed
            if xlo < b < xhi:
                bx = round(box[0] + (b - xlo) / (xhi - xlo) * (box[2] - box[0]))
                for yy in range(box[1], box[3], 6):
                    cv2.line(img, (bx, yy), (bx, min(yy + 3, box[3])), GRID_BGR, 1)
        for r in np.unique(run):
            seg = pts[run == r]
            if term == "flow_score" or len(seg) == 1:
                for p in seg:
                    cv2.circle(img, (int(p[0]), int(p[1])), 1, CURVE_BGR, -1, cv2.LINE_AA)
            if len(seg) > 1:
                cv2.polylines(img, [seg.reshape(-1, 1, 2)], False, CURVE_BGR, 1, cv2.LINE_AA)
        for val, yy in ((hi, box[1] + 8), (lo, box[3])):
            cv2.putText(img, f"{val:.3g}", (2, yy), font, small, TEXT_BGR, 1, cv2.LINE_AA)
        for val, xx in ((xlo, box[0]), (xhi, box[2] - 30)):
            cv2.putText(img, f"{val:.0f}", (xx, PANEL_H - 6), font, small, TEXT_BGR, 1, cv2.LINE_AA)
    return img


def loss_curves(path: Path, log: list, vgg_random: bool) -> None:
    """loss_curves.png: one panel per logged term (log scale where it stays positive), the phases' boundaries
    dashed. Drawn with OpenCV: matplotlib's tick layout for a dozen log axes took 1.6 s of Python holding the GIL
    while the other output threads encode."""
    shown = [t for t in LOG_TERMS if any(r.get(t, 0) != 0 for r in log)]
    shown += ["flow_score"] if any("flow_score" in r for r in log) else []
    bounds = [r["step"] for a, r in zip(log, log[1:]) if a["phase"] != r["phase"]]
    cols = 3
    rows = max(1, math.ceil(len(shown) / cols))
    grid = np.full((rows * PANEL_H, cols * PANEL_W, 3), 255, np.uint8)
    for i, t in enumerate(shown):
        r, c = divmod(i, cols)
        grid[r * PANEL_H:(r + 1) * PANEL_H, c * PANEL_W:(c + 1) * PANEL_W] = _panel(log, t, bounds)
    title = ["stylize losses per iteration (phases: pre | stylize | post)"] + ([RANDOM_VGG_NOTE] if vgg_random else [])
    head = _text_block(title, grid.shape[1], 0.5, (0, 0, 200) if vgg_random else TEXT_BGR)
    write_image(path, np.ascontiguousarray(np.concatenate([head, grid], 0)[..., ::-1]))  # write_image takes RGB


OUTPUT_WORKERS = min(8, os.cpu_count() or 1)  # threads that encode and score the outputs beside the GPU renders


def write_view(out: Path, i: int, sty: torch.Tensor, org: torch.Tensor, photo: torch.Tensor, fld, keep: bool) -> tuple:
    """One view's renders/, originals/, photos/ and fields/ files, and the flow alignment of the stylized and
    the original render to its target field (None without fields); the three images as numpy when ``keep``
    (a row of comparison.png), else None (no view's render outlives its job)."""
    from ..losses import flow_alignment_score  # lazy: imports Warp

    write_image(out / "renders" / f"view_{i:03d}.png", sty)
    write_image(out / "originals" / f"view_{i:03d}.png", org)
    write_image(out / "photos" / f"view_{i:03d}.png", photo)
    score = score_orig = None
    if fld is not None:
        with atomic_path(out / "fields" / f"view_{i:03d}.npy") as tmp:
            np.save(tmp, fld.astype(np.float32))
        score, score_orig = flow_alignment_score(sty.numpy(), fld), flow_alignment_score(org.numpy(), fld)
    return (sty.numpy(), org.numpy(), photo.numpy()) if keep else None, score, score_orig


# painted outside the scene's outline, as a share of the pixels the scene covers: worth a note from this share on (the
# biker splats at 512x384 under the default: 0.059-0.123 under five of six paintings, 0.048 under the sixth; lego
# 0.021-0.034; the biker with loss.w_silhouette=100: 0.026-0.041; docs/study.md, "The silhouette held ten times harder")
SPILL_NOTE = 0.05


def spill_counts(alpha: torch.Tensor, coverage: torch.Tensor) -> tuple[int, int, int]:
    """One view's (pixels the stylized render ``alpha`` [H,W] covers where the un-stylized scene's ``coverage``
    [H,W] does not, pixels the un-stylized scene covers, all pixels); covered = alpha at least 0.5, as `evaluate`'s
    spill and holes count."""
    was = coverage >= HOLE_ALPHA
    return int(((alpha >= HOLE_ALPHA) & ~was).sum()), int(was.sum()), was.numel()


def spill_note(share: float | None, w_silhouette: float) -> str | None:
    """One line for the user when the stylized scene paints ``SPILL_NOTE`` or more of the scene's covered area
    outside its outline (``share``: metrics.json's outside_outline_of_covered): a figure on an empty background swells. It
    names the silhouette weight to use (100 where the run had none, ten times the run's otherwise), on the empty
    pixels alone so that nothing the scene covers moves. None below the share (or None: nothing covered)."""
    if share is None or not share >= SPILL_NOTE:
        return None
    fix = 10 * w_silhouette if w_silhouette > 0 else 100
    return (f"note: the stylized scene paints {share:.0%} of its own area outside the scene's outline (pixels the "
            f"un-stylized scene leaves empty); --set loss.w_silhouette={fix:g} --set loss.silhouette_where=empty "
            f"holds the outline (this run: {w_silhouette:g})")


def _timed(fn, *args) -> tuple:
    """(fn(*args), its wall seconds)."""
    t = time.perf_counter()
    return fn(*args), time.perf_counter() - t


def write_orbit(out: Path, frames: list, fps: int) -> str | None:
    """orbit.mp4; PNG frames in orbit_frames/ when no encoder works. Returns the note to show (or None)."""
    try:
        note = write_video(out / "orbit.mp4", frames, fps)
    except RuntimeError as e:  # no working encoder (a full disk is a WriteError and stops the run)
        note = f"orbit.mp4 not written ({e}); frames are in orbit_frames/"
        for k, f in enumerate(frames):
            write_image(out / "orbit_frames" / f"frame_{k:04d}.png", f)
    if note:
        print(note)
    return note


def write_outputs(out: Path, res, *, input_bytes: int | None = None, wall_start: float | None = None,
                  progress: bool = False) -> dict:
    """Write every output file of a finished run; returns the metrics (also in metrics.json)."""
    from ..losses import field_picture  # lazy: imports Warp
    from ..losses.palette import covered_luminance_sums

    t0 = time.perf_counter()
    out = Path(out)
    cfg, inp = res.config, res.inputs
    g = res.gaussians
    bad = sum(int((~torch.isfinite(getattr(g, f))).sum()) for f in Gaussians.FIELDS)
    if bad:
        raise RuntimeError(f"refusing to write a PLY with {bad} non-finite values")
    g_cpu = g.to(device="cpu", dtype=torch.float32)
    bg = tuple(float(v) for v in cfg.background)  # run_stylize records the background it used
    # The GPU renders in this thread; the encoding and scoring (PNG, PLY formats, video, flow scores: numpy,
    # OpenCV and ffmpeg, which release the GIL) run in a pool beside it: they were most of the outputs' time.
    with ThreadPoolExecutor(max_workers=OUTPUT_WORKERS) as pool:
        jobs = [pool.submit(save_ply, g_cpu, out / "stylized.ply")]
        if cfg.web_formats:  # the same scene for browser viewers (SuperSplat, PlayCanvas, SPZ)
            jobs += [pool.submit(save_compressed_ply, g_cpu, out / "stylized.compressed.ply"),
                     pool.submit(save_spz, g_cpu, out / "stylized.spz")]
        write_json(out / "cameras.json", cameras_json(SimpleNamespace(cameras=inp.cameras, names=inp.names)))
        # where the inputs came from (evaluate and view find the un-stylized scene by it once checkpoint.pt is gone)
        write_json(out / "sources.json", {str(k): str(v) for k, v in (inp.sources or {}).items() if v is not None})
        pick = set(np.linspace(0, len(inp.cameras) - 1, min(cfg.comparison_views, len(inp.cameras))).round().astype(int))
        views, t = [], time.perf_counter()
        tone = [0.0, 0.0]  # the stylized renders' luminance summed over the covered pixels, and their count
        spill = [0, 0, 0]  # pixels painted outside the un-stylized scene's outline, pixels it covers, all pixels
        with torch.no_grad():  # the orbit first: its encoding is the longest job
            frames = [to_u8(render(g, cam, bg).color) for cam in orbit_path(inp.cameras, cfg.orbit_frames)]  # uint8
            video = pool.submit(_timed, write_orbit, out, frames, cfg.orbit_fps) if frames else None
            for i, cam in enumerate(inp.cameras):
                r = render(g, cam, bg)
                sty = r.color.clamp(0, 1).cpu()
                if i < len(res.coverage):
                    tone = [a + b for a, b in zip(tone, covered_luminance_sums(sty, res.coverage[i]))]
                    spill = [a + b for a, b in zip(spill, spill_counts(r.alpha.cpu(), res.coverage[i]))]
                fld = res.fields[i][..., :2].numpy() if res.fields else None
                views.append(pool.submit(write_view, out, i, sty, res.originals[i], inp.photos[i].detach().cpu(), fld,
                                         i in pick))
        split = {"renders": time.perf_counter() - t}  # the GPU's part (orbit frames and views), in this thread
        style_np = inp.style.detach().cpu().numpy()
        s_theta, s_coh, _ = res.style_field
        jobs += [pool.submit(write_image, out / "style.png", style_np),
                 pool.submit(lambda: write_image(out / "stroke_field.png",
                                                 field_picture(res.style_work.numpy(), s_theta, s_coh))),
                 pool.submit(loss_curves, out / "loss_curves.png", res.log, res.vgg_random)]
        done = [v.result() for v in views]  # ((stylized, original, photo) or None, score, original's score)
        scores = [d[1] for d in done if d[1] is not None]
        scores_orig = [d[2] for d in done if d[2] is not None]
        fa = float(np.mean(scores)) if scores else 0.0
        caption = comparison_caption(cfg, res.metrics["iterations"], fa) + "; " + (
            RANDOM_VGG_NOTE if res.vgg_random else f"VGG-16 weights: {weights_name(res.vgg_source)}")
        rows = [(ph, org, sty) for (sty, org, ph), _, _ in (d for d in done if d[0] is not None)]
        write_image(out / "comparison.png", comparison_grid(rows, style_np, caption).astype(np.float32) / 255.0)
        split["views_done"] = time.perf_counter() - t0  # every view's files written and scored
        video_note, split["video"] = video.result() if video is not None else (None, 0.0)
        for j in jobs:
            j.result()
    web = {f"bytes_out_{k}": os.path.getsize(out / f"stylized.{k.replace('_', '.')}")
           for k in ("compressed_ply", "spz")} if cfg.web_formats else {}

    m = dict(res.metrics)
    out_bytes = os.path.getsize(out / "stylized.ply")
    m.update({
        # the run's own score: its renders against the stroke field IT trained toward (differs between configs);
        # `evaluate` scores "flow_alignment" against one common field per view, the same for every run
        "training_field_alignment": fa,
        "training_field_alignment_per_view": [round(s, 5) for s in scores],
        "training_field_alignment_unstylized": float(np.mean(scores_orig)) if scores_orig else 0.0,
        # the stylized views' mean luminance over the pixels the un-stylized scene covers (beside "tone_target",
        # the colour target's over the same pixels): how far the run moved the scene's tone from its palette's
        "tone_covered": tone[0] / tone[1] if tone[1] else None,
        # painted where the un-stylized scene leaves the view empty, over every view at the training size (what
        # `evaluate` calls spill over the views it scores; one name per number), and the same pixels as a share of
        # the area the scene covers (what `stylize`'s note reads)
        "outside_outline": spill[0] / spill[2] if spill[2] else None,
        "outside_outline_of_covered": spill[0] / spill[1] if spill[1] else None,
        "field_mapping": cfg.loss.field_mapping,
        "bytes_in": int(input_bytes) if input_bytes is not None else int(inp.gaussians.nbytes()),
        "bytes_out": int(out_bytes),
        **web,
        "sh_degree_out": g.sh_degree,
        "views": list(inp.names),
        "orbit": video_note or "orbit.mp4",
        "vgg_note": RANDOM_VGG_NOTE if res.vgg_random else "pretrained",
        "outputs_time_s": round(time.perf_counter() - t0, 3),
        "outputs_split_s": {k: round(v, 3) for k, v in split.items()},  # renders; views written by; video encode
    })
    if wall_start is not None:
        m["wall_time_s"] = round(time.perf_counter() - wall_start, 3)
    final_log = [r for r in res.log if "flow_score" in r]
    m["final_losses"] = {k: v for k, v in (res.log[-1] if res.log else {}).items() if isinstance(v, float)}
    m["flow_score_log"] = [[r["step"], r["flow_score"]] for r in final_log]
    write_json(out / "metrics.json", m)
    return m


__all__ = ["write_outputs", "comparison_grid", "zoom_crop", "wrap_text", "font_scale", "orbit_path", "write_video",
           "loss_curves", "curve", "panel_points", "RANDOM_VGG_NOTE", "comparison_caption", "spill_counts",
           "spill_note", "SPILL_NOTE"]
