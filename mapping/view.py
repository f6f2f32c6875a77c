"""PNG top view of the map (north up, east right): planes as segments, robot tracks as lines."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lrsensor.plots import pyplot


def plot_top_view(
    path: Path,
    planes: Sequence[Mapping[str, Any]],
    tracks: Mapping[str, Sequence[Sequence[float]]] | None = None,
    title: str = "shared map (top view, NED)",
) -> None:
    """Draw the map seen from above and save it as a PNG.

    Args:
        path: output PNG.
        planes: plane dicts as in ``MapBuilder.map_json()["planes"]``.
        tracks: robot -> samples ``(t_ns, north_m, east_m, down_m)``.
        title: figure title.

    Near-vertical planes are drawn as segments along their horizontal extent, with a short tick along the normal
    (toward the side the robots saw them from); near-horizontal planes as outlines.
    """
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 8))
    for p in planes:
        n = np.asarray(p["normal"], dtype=float)
        corners = np.asarray(p["extent"]["corners"], dtype=float)
        ne = corners[:, :2]
        if abs(n[2]) < 0.7:
            a = 0.5 * (ne[0] + ne[3])
            b = 0.5 * (ne[1] + ne[2])
            ax.plot([a[1], b[1]], [a[0], b[0]], "-", color="tab:blue", lw=2.5)
            mid = 0.5 * (a + b)
            h = n[:2] / max(float(np.linalg.norm(n[:2])), 1e-9) * 0.15
            ax.plot([mid[1], mid[1] + h[1]], [mid[0], mid[0] + h[0]], "-", color="tab:blue", lw=1)
            ax.annotate(str(p["id"]), (mid[1] + h[1], mid[0] + h[0]), fontsize=7, color="tab:blue")
        else:
            loop = np.vstack([ne, ne[:1]])
            ax.plot(loop[:, 1], loop[:, 0], "--", color="tab:gray", lw=1)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"][1:]
    for k, (robot, samples) in enumerate(sorted((tracks or {}).items())):
        arr = np.asarray(samples, dtype=float).reshape(-1, 4)
        if arr.shape[0] == 0:
            continue
        c = colors[k % len(colors)]
        ax.plot(arr[:, 2], arr[:, 1], "-", color=c, lw=1, label=robot)
        ax.plot(arr[0, 2], arr[0, 1], "o", color=c, ms=4)
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.set_title(f"{title}: {len(planes)} planes")
    if tracks:
        ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
