"""What the benchmarks' figures share: labelled image panels and writing a matplotlib figure."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def labelled(image: np.ndarray, text: str) -> np.ndarray:
    """A copy of an (H, W, 3) uint8 RGB panel with `text` on a dark band at its top left."""
    import cv2

    out = np.array(image, copy=True)
    scale = max(0.4, out.shape[0] / 768 * 0.9)
    thick = max(1, int(round(scale * 2)))
    text = text.replace("α", "a").replace("≈", "~").replace("×", "x")  # Hershey fonts are ASCII
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thick)
    out[: h + base + 8, : w + 10] //= 3
    cv2.putText(out, text, (5, h + 4), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), thick, cv2.LINE_AA)
    return out


def save_figure(fig, path: Path) -> str:
    """Lay out, write and close a figure; returns the path written."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)
    return str(path)
