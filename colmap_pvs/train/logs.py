"""The run's log files: the CSV logs and the loss curves (``loss.png``, drawn with OpenCV)."""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..io.files import atomic_write_bytes

_COLOURS = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
            (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)]  # fmt: skip


def plot_curves(
    path: Path,
    series: dict[str, tuple[list[float], list[float]]],
    *,
    title: str = "",
    size=(960, 540),
    xlabel: str = "step",
    log_y: bool = True,
) -> Path | None:
    """Draw ``{name: (xs, values)}`` as line curves (log10 y axis unless ``log_y=False``) into a PNG
    with OpenCV.

    Non-finite (and, on a log axis, non-positive) values are skipped. Returns the path, or ``None``
    when there is nothing to draw. Written atomically.
    """
    clean = {}
    for name, (xs, ys) in series.items():
        pts = [
            (float(x), math.log10(y) if log_y else float(y))
            for x, y in zip(xs, ys, strict=True)
            if math.isfinite(y) and (y > 0 or not log_y)
        ]
        if pts:
            clean[name] = pts
    if not clean:
        return None
    W, H = size
    left, right, top, bottom = 80, 20, 40, 50
    img = np.full((H, W, 3), 255, np.uint8)
    allx = [p[0] for pts in clean.values() for p in pts]
    ally = [p[1] for pts in clean.values() for p in pts]
    x0, x1 = min(allx), max(allx)
    if log_y:
        y0, y1 = math.floor(min(ally) * 2) / 2, math.ceil(max(ally) * 2) / 2
        y1 = y1 if y1 > y0 else y0 + 0.5
        ticks = np.arange(y0, y1 + 1e-9, 0.5 if y1 - y0 <= 4 else 1.0)
    else:
        pad = 0.05 * (max(ally) - min(ally)) or 0.05 * abs(max(ally)) or 1.0
        y0, y1 = min(ally) - pad, max(ally) + pad
        ticks = np.linspace(y0, y1, 6)
    x1 = x1 if x1 > x0 else x0 + 1

    def px(x: float, y: float) -> tuple[int, int]:
        return (
            int(round(left + (x - x0) / (x1 - x0) * (W - left - right))),
            int(round(H - bottom - (y - y0) / (y1 - y0) * (H - top - bottom))),
        )

    font = cv2.FONT_HERSHEY_SIMPLEX
    grey = (200, 200, 200)
    for t in ticks:
        a, b = px(x0, t), px(x1, t)
        cv2.line(img, a, b, grey, 1)
        label = f"{10**t:.3g}" if log_y else f"{t:.3g}"
        cv2.putText(img, label, (5, a[1] + 4), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    xs_unique = sorted(set(allx))
    integer_x = len(xs_unique) <= 12 and all(float(x).is_integer() for x in xs_unique)
    for t in xs_unique if integer_x else np.linspace(x0, x1, 6):  # few integer x values: tick each
        a = px(t, y0)
        cv2.line(img, a, (a[0], a[1] + 5), (0, 0, 0), 1)
        cv2.putText(img, f"{t:.0f}", (a[0] - 15, a[1] + 20), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.rectangle(img, px(x0, y1), px(x1, y0), (0, 0, 0), 1)
    cv2.putText(img, xlabel, (W // 2 - 15, H - 8), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, title, (left, 25), font, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    text_w = max(cv2.getTextSize(name, font, 0.45, 1)[0][0] for name in clean)
    lx = W - right - text_w - 40
    for i, (name, pts) in enumerate(clean.items()):
        rgb = _COLOURS[i % len(_COLOURS)]
        colour = (rgb[2], rgb[1], rgb[0])
        poly = np.array([px(x, y) for x, y in pts], np.int32)
        if len(poly) == 1:
            cv2.circle(img, tuple(int(v) for v in poly[0]), 3, colour, -1, cv2.LINE_AA)
        else:
            cv2.polylines(img, [poly], False, colour, 2 if i == 0 else 1, cv2.LINE_AA)
        ly = top + 15 + 18 * i
        cv2.line(img, (lx, ly - 4), (lx + 25, ly - 4), colour, 2)
        cv2.putText(img, name, (lx + 30, ly), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    ok, buf = cv2.imencode(".png", img)
    if not ok:  # pragma: no cover - OpenCV failure
        raise OSError(f"cannot encode the loss plot {str(path)!r}")
    return atomic_write_bytes(path, buf.tobytes())


def _read_csv(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    if not path.is_file():
        return [], []
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        return list(reader.fieldnames or []), list(reader)


def _write_csv(path: Path, columns: list[str], rows: list[dict[str, Any]]) -> None:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_bytes(path, buf.getvalue().encode())


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return repr(value)
    return str(value)
