"""Animated GIF of the balls in the jar: DEM and surrogate side by side (``sgn-jax demo``).

Layout of each frame (lab frame; axes in mm)::

    t = ... s since the start of motion   E_DEM = ... mJ   E_model = ... mJ
    +-------------------------------+---------------------------------+
    | DEM (reference): top view     | model (surrogate): top view     |  x-z, section at mid-height
    +-------------------------------+---------------------------------+
    | DEM (reference): side view    | model (surrogate): side view    |  x-y, section at z = 0
    +-------------------------------+---------------------------------+

The jar outline comes from the jar's own geometry (plane sections of its cavity mesh, which the
caller builds with :func:`sgn_jax.pipelines.configure.jar_mesh_from_config`, so STL jars and the
central post are drawn as they are) and moves with the jar offset. Each ball keeps its colour in all
four panels, so a ball of the surrogate can be followed against the same ball of the DEM.

Rendering uses matplotlib's object API with the Agg canvas (nothing global, no display): the
figure and its artists are built once and only moved per frame, which keeps ~100 frames at a
few seconds. Frames are quantised to one shared palette and written with Pillow as a looping
GIF, atomically.

- :func:`jar_sections`: jar-frame outline segments for the two views.
- :func:`select_frames`: ~n evenly spaced frame indices including the first and the last.
- :func:`write_comparison_gif`: the animation.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from sgn_jax.records.io_utils import atomic_write

# Layout of the GIF's figure (inches): tick labels and axis titles around the four panels.
_MARGIN_LEFT_IN, _MARGIN_RIGHT_IN, _GAP_X_IN = 0.5, 0.1, 0.5
_HEADER_IN, _MARGIN_BOTTOM_IN, _GAP_Y_IN = 0.62, 0.34, 0.5


def _mm(value: float, _position: Any = None) -> str:
    """Tick label of a coordinate in metres, written in mm."""
    return f"{1e3 * value:.0f}"


class JarSections(NamedTuple):
    """Jar-frame outline segments (m) of the two views.

    top: (K, 2, 2) segments in (x, z), the section by the horizontal plane at mid-height;
    side: (L, 2, 2) segments in (x, y), the section by the vertical plane z = 0;
    lower, upper: (3,) jar-frame bounding box of the cavity.
    """

    top: np.ndarray
    side: np.ndarray
    lower: np.ndarray
    upper: np.ndarray


def jar_sections(mesh: Any) -> JarSections:
    """Outline segments of a jar's cavity mesh (a ``trimesh.Trimesh`` in the jar frame, m; for a
    ``[jar]`` config section: :func:`sgn_jax.pipelines.configure.jar_mesh_from_config`).

    The top view cuts the cavity mesh at mid-height, the side view at z = 0 (the jar axis plane
    for the parametric jar); both come from ``trimesh.intersections.mesh_plane``.
    """
    from trimesh.intersections import mesh_plane

    lower, upper = (np.asarray(b, dtype=np.float64) for b in mesh.bounds)
    mid_height = 0.5 * (lower[1] + upper[1])
    top = np.asarray(mesh_plane(mesh, [0.0, 1.0, 0.0], [0.0, mid_height, 0.0]), np.float64)
    side = np.asarray(mesh_plane(mesh, [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]), np.float64)
    if top.size == 0 or side.size == 0:
        raise ValueError("the jar mesh has no section at mid-height or at z = 0; is the jar "
                         "frame's origin at the centre of the jar floor (docs/conventions.md "
                         "section 1)?")
    return JarSections(top=top[..., [0, 2]], side=side[..., [0, 1]], lower=lower, upper=upper)


def select_frames(n_available: int, n_frames: int) -> np.ndarray:
    """About ``n_frames`` evenly spaced indices into ``n_available`` frames, first and last
    included, strictly increasing (all of them if there are fewer)."""
    if n_available < 1:
        raise ValueError(f"no frames to animate (n_available = {n_available})")
    if n_frames < 2:
        raise ValueError(f"n_frames must be >= 2, got {n_frames}")
    if n_available <= n_frames:
        return np.arange(n_available)
    return np.unique(np.rint(np.linspace(0, n_available - 1, n_frames)).astype(np.int64))


def _ball_colors(n_balls: int) -> np.ndarray:
    """(N, 4) RGBA: distinct hues so each ball can be followed in all panels."""
    from matplotlib import colormaps

    cmap = colormaps["tab20"] if n_balls <= 20 else colormaps["hsv"]
    steps = np.arange(n_balls) / (20 if n_balls <= 20 else n_balls)
    return np.asarray(cmap(steps))


def write_comparison_gif(
    path: str | Path,
    t: Any,
    pos_dem: Any,
    pos_sgn: Any,
    offsets: Any,
    jar_mesh: Any,
    ball_radius: float,
    *,
    captions: Sequence[str] | None = None,
    fps: float = 10.0,
    width_px: int = 760,
    progress: bool = True,
) -> Path:
    """Write the side-by-side animation (DEM left, model right; top and side views) as a GIF.

    Every panel is titled with its source (DEM or model) and view and has axes in mm; the
    figure's title gives the time of the frame (and the captions).

    Args:
        path: output ``.gif``.
        t: (F,) s, the time of each frame (shown in the title).
        pos_dem, pos_sgn: (F, N, 3) m, lab-frame ball centres of the DEM and the surrogate at
            the frame times, balls matched by index.
        offsets: (F, 3) m, jar offset at the frame times (the outline moves with it).
        jar_mesh: the jar's cavity mesh in the jar frame (``trimesh.Trimesh``, m;
            :func:`sgn_jax.pipelines.configure.jar_mesh_from_config` of the ``[jar]`` section).
        ball_radius: m.
        captions: optional (F,) strings appended to each frame's title (e.g. the energies).
        fps: frames per second of the GIF.
        width_px: image width in pixels (the height follows the jar's aspect ratio).
        progress: tqdm bar over the frames.
    Returns:
        the path written.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle
    from matplotlib.ticker import FuncFormatter
    from PIL import Image
    from tqdm.auto import tqdm

    path = Path(path)
    if path.suffix.lower() != ".gif":
        raise ValueError(f"animation path {str(path)!r} must end in '.gif'")
    t = np.asarray(t, dtype=np.float64)
    pos_dem = np.asarray(pos_dem, dtype=np.float64)
    pos_sgn = np.asarray(pos_sgn, dtype=np.float64)
    offsets = np.asarray(offsets, dtype=np.float64)
    n_frames = t.shape[0]
    if t.ndim != 1 or n_frames < 1:
        raise ValueError(f"t must be (F,) frame times with F >= 1, got shape {t.shape}")
    if pos_dem.ndim != 3 or pos_dem.shape[0] != n_frames or pos_dem.shape[2] != 3:
        raise ValueError(f"pos_dem must be (F, N, 3) with F = {n_frames}, got {pos_dem.shape}")
    if pos_sgn.shape != pos_dem.shape:
        raise ValueError(f"pos_sgn must have the shape of pos_dem {pos_dem.shape}, got "
                         f"{pos_sgn.shape}")
    if offsets.shape != (n_frames, 3):
        raise ValueError(f"offsets must be ({n_frames}, 3), got {offsets.shape}")
    if captions is not None and len(captions) != n_frames:
        raise ValueError(f"captions must have one string per frame ({n_frames}), got "
                         f"{len(captions)}")
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")

    sections = jar_sections(jar_mesh)
    n_balls = pos_dem.shape[1]
    colors = _ball_colors(n_balls)

    # Fixed axes that hold the jar at every offset of the animation, plus a margin.
    margin = 0.1 * float(np.max(sections.upper - sections.lower))
    x_lim = (sections.lower[0] + offsets[:, 0].min() - margin,
             sections.upper[0] + offsets[:, 0].max() + margin)
    z_lim = (sections.lower[2] + offsets[:, 2].min() - margin,
             sections.upper[2] + offsets[:, 2].max() + margin)
    y_lim = (sections.lower[1] + offsets[:, 1].min() - margin,
             sections.upper[1] + offsets[:, 1].max() + margin)
    x_span, z_span, y_span = (b - a for a, b in (x_lim, z_lim, y_lim))
    # Layout in inches: two columns of x_span wide panels (rows z_span and y_span tall, equal
    # aspect), margins for the tick labels and axis titles, a header for the title lines.
    width_in = 7.0
    left, right, gap_x = _MARGIN_LEFT_IN, _MARGIN_RIGHT_IN, _GAP_X_IN
    top, bottom, gap_y = _HEADER_IN, _MARGIN_BOTTOM_IN, _GAP_Y_IN
    panel_w = 0.5 * (width_in - left - right - gap_x)
    heights = (panel_w * z_span / x_span, panel_w * y_span / x_span)
    height_in = top + heights[0] + gap_y + heights[1] + bottom
    dpi = width_px / width_in

    fig = Figure(figsize=(width_in, height_in), dpi=dpi)
    FigureCanvasAgg(fig)
    title = fig.suptitle("", fontsize=9, y=1.0 - 0.05 / height_in, va="top")
    fig.text(0.5, 1.0 - 0.27 / height_in, "left: DEM (reference)   right: model (surrogate)   "
             "lab frame, mm; one colour per ball, the same in all panels", fontsize=7,
             ha="center", va="top", color="0.3")
    # Per panel: axes, positions, the two drawn coordinates, the depth coordinate (what is
    # nearer the viewer is drawn on top: larger y seen from above, larger z seen from the
    # front), outline, its segments, the circles.
    panels = []
    for column, (label, positions) in enumerate((("DEM (reference)", pos_dem),
                                                  ("model (surrogate)", pos_sgn))):
        for row, (view, coords, depth, segments, lims) in enumerate((
                ("top view, section at mid-height", (0, 2), 1, sections.top, (x_lim, z_lim)),
                ("side view, section at z = 0", (0, 1), 2, sections.side, (x_lim, y_lim)))):
            x0 = left + column * (panel_w + gap_x)
            y0 = bottom + (heights[1] + gap_y if row == 0 else 0.0)
            ax = fig.add_axes((x0 / width_in, y0 / height_in, panel_w / width_in,
                               heights[row] / height_in))
            ax.set_xlim(*lims[0])
            ax.set_ylim(*lims[1])
            ax.set_aspect("equal")
            ax.xaxis.set_major_formatter(FuncFormatter(_mm))
            ax.yaxis.set_major_formatter(FuncFormatter(_mm))
            ax.tick_params(labelsize=6, length=2, pad=1)
            ax.set_xlabel("x (mm)", fontsize=7, labelpad=1)
            ax.set_ylabel(("z (mm)", "y (mm)")[row], fontsize=7, labelpad=1)
            ax.set_title(f"{label}: {view}", fontsize=8, pad=2,
                         fontweight="bold" if row == 0 else "normal")
            outline = LineCollection(segments, colors="dimgrey", linewidths=1.2, zorder=3)
            ax.add_collection(outline)
            circles = []
            for b in range(n_balls):
                circle = Circle((0.0, 0.0), ball_radius, facecolor=colors[b],
                                edgecolor="black", linewidth=0.4, alpha=0.85)
                ax.add_patch(circle)
                circles.append(circle)
            panels.append((positions, coords, depth, outline, segments, circles))

    images = []
    palette_image = None
    for f in tqdm(range(n_frames), desc="animation", unit="frame", disable=not progress,
                  dynamic_ncols=True):
        for positions, (a, b), depth, outline, segments, circles in panels:
            shift = np.array([offsets[f, a], offsets[f, b]])
            outline.set_segments(segments + shift)
            rank = np.argsort(np.argsort(positions[f, :, depth]))
            for circle, centre, r in zip(circles, positions[f], rank, strict=True):
                circle.set_center((centre[a], centre[b]))
                circle.set_zorder(2.0 + 1e-3 * r)
        text = f"t = {t[f]:.3f} s since the start of motion"
        if captions is not None:
            text += "   " + captions[f]
        title.set_text(text)
        fig.canvas.draw()
        rgb = Image.fromarray(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
        # One palette for all frames: no colour flicker, and LZW compresses the flat areas.
        if palette_image is None:
            palette_image = rgb.quantize(colors=96, method=Image.Quantize.MEDIANCUT)
            images.append(palette_image)
        else:
            images.append(rgb.quantize(palette=palette_image, dither=Image.Dither.NONE))

    duration_ms = int(round(1000.0 / fps))
    with atomic_write(path, "wb") as fh:
        images[0].save(fh, format="GIF", save_all=True, append_images=images[1:],
                       duration=duration_ms, loop=0, optimize=False, disposal=1)
    return path


def gif_frame_count(path: str | Path) -> int:
    """Number of frames of a GIF file."""
    from PIL import Image

    with Image.open(path) as image:
        return int(getattr(image, "n_frames", 1))


__all__ = [
    "JarSections",
    "gif_frame_count",
    "jar_sections",
    "select_frames",
    "write_comparison_gif",
]
