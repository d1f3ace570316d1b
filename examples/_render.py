"""Matplotlib figures shared by the examples (Agg backend: PNG files, no display needed)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np

BOX = ((-1.5, 1.5), (-1.1, 1.1), (-1.1, 1.1))


def draw_surface(ax, points, triangles, *, colour_by=None, cmap="viridis", clim=None, colour="tab:blue", alpha=1.0, title=""):
    """One triangle surface in a 3-D axis: flat colour, or per-face colours from ``colour_by``."""
    points = np.asarray(points)
    triangles = np.asarray(triangles)
    surf = ax.plot_trisurf(points[:, 0], points[:, 1], points[:, 2], triangles=triangles, linewidth=0.0,
                           antialiased=False, color=colour, alpha=alpha, shade=colour_by is None)
    if colour_by is not None:
        face_values = np.asarray(colour_by)
        if face_values.shape[0] == points.shape[0]:
            face_values = face_values[triangles].mean(1)
        surf.set_array(face_values)
        surf.set_cmap(cmap)
        surf.set_clim(*(clim if clim is not None else (face_values.min(), max(face_values.max(), face_values.min() + 1e-9))))
    ax.set_title(title)
    ax.set_xlim(*BOX[0]), ax.set_ylim(*BOX[1]), ax.set_zlim(*BOX[2])
    ax.set_box_aspect([hi - lo for lo, hi in BOX], zoom=1.3)
    ax.view_init(elev=20, azim=-60)
    ax.set_axis_off()
    return surf


def figure_of_surfaces(path: Path, panels: Sequence[dict], *, panel_size: float = 4.0, colorbar_label: str | None = None, columns: int | None = None) -> None:
    """Save a row (or grid) of 3-D surface panels; each panel is ``draw_surface``'s keywords."""
    columns = columns or len(panels)
    rows = -(-len(panels) // columns)
    fig = plt.figure(figsize=(panel_size * columns, panel_size * rows))
    for i, panel in enumerate(panels):
        ax = fig.add_subplot(rows, columns, i + 1, projection="3d")
        surf = draw_surface(ax, **panel)
        if colorbar_label is not None and panel.get("colour_by") is not None:
            fig.colorbar(surf, ax=ax, shrink=0.6, label=colorbar_label)
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.0, top=0.86, wspace=0.0, hspace=0.1)
    save(fig, path)


def overlay_with_target(path: Path, stages: Sequence[tuple[str, np.ndarray]], triangles, target_points, target_triangles) -> None:
    """Panels of surfaces (coloured) over the target (translucent grey), e.g. before and after."""
    fig = plt.figure(figsize=(4.5 * (len(stages) + 1), 4.5))
    ax = fig.add_subplot(1, len(stages) + 1, 1, projection="3d")
    draw_surface(ax, target_points, target_triangles, colour="tab:orange", title="target")
    for i, (title, points) in enumerate(stages):
        ax = fig.add_subplot(1, len(stages) + 1, i + 2, projection="3d")
        draw_surface(ax, target_points, target_triangles, colour="0.6", alpha=0.25)
        draw_surface(ax, points, triangles, colour="tab:blue", title=title)
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.0, top=0.92, wspace=0.0)
    save(fig, path)


def loss_curves(path: Path, panels: dict[str, dict[str, Sequence[float]]], *, title: str = "", xlabel: str = "iteration") -> None:
    """Histories on log scales, one subplot per ``{panel title: {label: values}}`` entry.

    Values that are not positive (a regulariser that is exactly zero) leave gaps; a curve that is
    zero throughout is named in the legend only.
    """
    fig, axes = plt.subplots(1, len(panels), figsize=(6 * len(panels), 4), squeeze=False)
    for ax, (panel_title, curves) in zip(axes[0], panels.items()):
        for label, values in curves.items():
            values = np.asarray(values, float)
            if not np.any(values > 0):
                ax.plot([], [], " ", label=f"{label}: 0 throughout")
                continue
            ax.semilogy(np.arange(len(values)), np.where(values > 0, values, np.nan), label=label)
        ax.set_xlabel(xlabel)
        ax.set_title(panel_title)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.suptitle(title)
    fig.tight_layout()
    save(fig, path)


def save(fig, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    print(f"wrote {path}")
