"""A picture of the plant for people: the six tank levels, which valves are
open on the shared conduit, and the centre of gravity on the wing's axis of
moment arms. Drawn with matplotlib's Agg backend into an RGB array (no window,
no pyplot global state), for ``FuelTransferEnv(render_mode="rgb_array")`` and
video wrappers.

Tanks are drawn where they sit: at their moment arms (-3 .. 3 m, the fuselage
at 0), left wing feeding engine E1, right wing E2.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ftc.common.constants import NUM_TANKS, TANK_HEIGHT
from ftc.plant.reward import MOMENT_ARMS

# Colours are part of the picture's legend (and what the render tests look for).
FUEL_RGB = (31, 119, 180)
OPEN_VALVE_RGB = (44, 160, 44)
CG_RGB = (214, 39, 40)


@dataclass(frozen=True)
class FrameConfig:
    """Size of a rendered frame: width x height pixels = (width_in, height_in) * dpi."""

    width_in: float = 6.4
    height_in: float = 4.0
    dpi: int = 100


def _hex(rgb: tuple[int, int, int]) -> str:
    return "#%02x%02x%02x" % rgb


def draw_plant(level: np.ndarray, valves: np.ndarray, cg: float, caption: str = "",
               config: FrameConfig = FrameConfig()) -> np.ndarray:
    """The plant as an image.

    level: (6,) tank levels, m (drawn clipped to [0, tank height])
    valves: (6,) 0/1, valve i open during the last step
    cg: centre of gravity, m along the moment arms (negative: left wing heavy)
    caption: a line of text under the title (step, age, reward)
    Returns (H, W, 3) uint8 RGB, H = height_in * dpi, W = width_in * dpi.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    level = np.clip(np.asarray(level, dtype=np.float64), 0.0, TANK_HEIGHT)
    valves = np.asarray(valves)
    if level.shape != (NUM_TANKS,) or valves.shape != (NUM_TANKS,):
        raise ValueError(f"draw_plant: level and valves must have shape ({NUM_TANKS},), "
                         f"got {level.shape} and {valves.shape}")
    fig = Figure(figsize=(config.width_in, config.height_in), dpi=config.dpi)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0.03, 0.02, 0.94, 0.84))
    ax.set_xlim(-3.7, 3.7)
    ax.set_ylim(-0.55, 1.45)
    ax.set_axis_off()
    width, conduit_y = 0.62, -0.2

    # the shared conduit, and a pipe from each tank's valve down to it
    ax.plot([MOMENT_ARMS[0], MOMENT_ARMS[-1]], [conduit_y, conduit_y], color="0.55", lw=3,
            solid_capstyle="butt", zorder=1)
    ax.axvline(0.0, color="0.8", lw=1, ls="--", zorder=0)
    for i, (x, h, u) in enumerate(zip(MOMENT_ARMS, level, valves)):
        ax.add_patch(Rectangle((x - width / 2, 0.0), width, h, facecolor=_hex(FUEL_RGB),
                               edgecolor="none", antialiased=False, zorder=2))
        ax.add_patch(Rectangle((x - width / 2, 0.0), width, TANK_HEIGHT, facecolor="none",
                               edgecolor="black", lw=1.5, zorder=3))
        is_open = bool(u)
        ax.text(x, TANK_HEIGHT + 0.07, f"{h:.2f} m", ha="center", va="center", fontsize=8,
                zorder=4)
        ax.plot([x, x], [0.0, conduit_y], color=_hex(OPEN_VALVE_RGB) if is_open else "0.55",
                lw=3 if is_open else 2, zorder=1)
        # a marker, not a Circle patch: round in pixels whatever the axes' aspect
        ax.plot([x], [conduit_y], marker="o", markersize=13, markeredgewidth=1.2,
                markeredgecolor="black", antialiased=False, zorder=5,
                markerfacecolor=_hex(OPEN_VALVE_RGB) if is_open else "white")
        ax.text(x, conduit_y - 0.2, f"T{i + 1} {'open' if is_open else 'shut'}", ha="center",
                va="center", fontsize=8, zorder=4)
    ax.text(-1.9, -0.5, "engine E1", ha="center", va="center", fontsize=8, color="0.3")
    ax.text(1.9, -0.5, "engine E2", ha="center", va="center", fontsize=8, color="0.3")

    # centre of gravity on the axis of moment arms, above the tanks
    axis_y = 1.2
    ax.plot([MOMENT_ARMS[0], MOMENT_ARMS[-1]], [axis_y, axis_y], color="black", lw=1, zorder=1)
    for x in (-3, -2, -1, 0, 1, 2, 3):
        ax.plot([x, x], [axis_y - 0.03, axis_y + 0.03], color="black", lw=1, zorder=1)
    cg_x = float(np.clip(cg, MOMENT_ARMS[0], MOMENT_ARMS[-1]))
    ax.plot([cg_x], [axis_y], marker="v", markersize=11, color=_hex(CG_RGB),
            antialiased=False, zorder=6)
    ax.text(3.65, axis_y + 0.13, f"cg {cg:+.3f} m", ha="right", va="center", fontsize=9,
            color=_hex(CG_RGB))
    fig.suptitle("fuel-transfer plant" + (f"\n{caption}" if caption else ""), fontsize=10,
                 y=0.98)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()
