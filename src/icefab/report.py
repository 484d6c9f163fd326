"""Pictures and the HTML build report.

The pictures of every stage live here (the commands only call them): layers
(:func:`plot_layers`), regions and paths (:func:`plot_toolpaths`), speed along the
trajectories (:func:`plot_speed`, thesis Fig. 4-11), the simulator's RMS
error vs height and error surfaces (:func:`plot_rms`, :func:`plot_surfaces`, thesis
Figs. 5-9 and 5-8) and the 1D SMF response (:func:`plot_error_response`).
Figures are written atomically (temporary file, then rename) so an interrupted command
never leaves a half-written picture. The HTML report is one self-contained file: every
picture is embedded, so it can be mailed or archived as it is.
"""

from __future__ import annotations

import base64
import dataclasses
import html
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Sequence

import numpy as np

from icefab.atomic import atomic_path
from icefab.feedback import simulate_1d
from icefab.core import (LayerPaths, RuledEdges, Stack, Toolpaths, area_text, closed_polyline,
                         true_runs)

if TYPE_CHECKING:  # pragma: no cover
    from icefab.config import Job
    from icefab.sim import SimResult

# Material colours shared by every picture: part (water) blue, scaffold orange.
_COLOUR = {"part": "tab:blue", "scaffold": "tab:orange"}
#: Drawing order of a layer's kinds of path in :func:`plot_toolpaths` (later on top).
_LINE_ORDER = {"travel": 0, "measure": 1, "fill": 2, "boundary": 3}


class _Figures:
    """The part of ``matplotlib.pyplot`` the pictures use, on plain ``Figure`` objects: no
    backend is chosen and no global figure list kept, so drawing a report leaves the
    caller's matplotlib (an interactive session, a notebook) as it was."""

    _FIGURE_KW = ("figsize", "dpi", "constrained_layout", "layout", "facecolor")

    @classmethod
    def subplots(cls, *args: Any, **kw: Any) -> tuple[Any, Any]:
        from matplotlib.figure import Figure

        fig = Figure(**{k: kw.pop(k) for k in cls._FIGURE_KW if k in kw})
        return fig, fig.subplots(*args, **kw)

    @staticmethod
    def close(fig: Any) -> None:
        """Nothing to release: the figure was never registered with pyplot."""


def pyplot() -> type[_Figures]:
    """What the pictures need of pyplot (``subplots``, ``close``), without pyplot: figures
    are ``matplotlib.figure.Figure`` objects saved by :func:`save_figure`."""
    return _Figures


def save_figure(fig: Any, path: str | os.PathLike, *, dpi: int = 110) -> Path:
    """Write a matplotlib figure as PNG to ``path`` atomically and close it."""
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=dpi, format="png")
    finally:
        pyplot().close(fig)
    return Path(path)


#: Words for the keys of the demo's summary.json in report.html (others: underscores to
#: spaces, a unit suffix such as ``_mm`` or ``_s`` shown as ", mm" / ", s").
LABELS = {
    "slice": "slicing", "paths": "paths", "motion": "trajectories", "valves": "valve programs",
    "simulation": "build simulator", "seconds": "time taken, s",
    "constant_speed_s": "constant-speed estimate (length / speed, no accelerations), s",
    "build_s": "build motion time, minimum-time trajectories, s",
    "samples": "trajectory samples", "pulses": "valve pulses", "pieces": "program pieces",
    "findings": "valve-limit findings", "warnings": "warnings", "layers": "layers",
    "final_rms_open_loop_mm": "final RMS height error, open loop, mm",
    "final_rms_smf_mm": "final RMS height error, with SMF, mm",
    "final_rms_footprint_open_loop_mm": "final RMS height error over the whole footprint "
                                        "(part and scaffold), open loop, mm",
    "final_rms_footprint_smf_mm": "final RMS height error over the whole footprint (part "
                                  "and scaffold), with SMF, mm",
}
_UNITS = {"mm": "mm", "s": "s", "mm2": "mm²", "mm3": "mm³", "h": "h", "hz": "Hz"}


def _label(key: str) -> str:
    if key in LABELS:
        return LABELS[key]
    head, _, unit = key.rpartition("_")
    if head and unit.lower() in _UNITS:
        return f"{head.replace('_', ' ')}, {_UNITS[unit.lower()]}"
    return key.replace("_", " ")


def _number(value: float) -> str:
    """A figure as people read it: thousands separated, about four significant digits,
    never an exponent between 1e-3 and 1e15 (``35,240``, ``2.716``, ``0.04912``)."""
    if not math.isfinite(value):
        return "n/a"
    a = abs(value)
    if a == 0:
        return "0"
    if a < 1e-3 or a >= 1e15:
        return f"{value:.3e}"
    decimals = max(0, 3 - int(math.floor(math.log10(a))))
    return f"{value:,.{decimals}f}"


def _rows(data: Mapping[str, Any], prefix: str = "") -> list[tuple[str, str]]:
    rows: list[tuple[str, str]] = []
    for key, value in data.items():
        name = f"{prefix}{_label(str(key))}"
        if isinstance(value, Mapping):
            rows += _rows(value, name + " / ")
        elif isinstance(value, float):
            rows.append((name, _number(value)))
        elif isinstance(value, int) and not isinstance(value, bool):
            rows.append((name, f"{value:,}"))
        elif isinstance(value, (list, tuple)):
            rows.append((name, "; ".join(str(v) for v in value) if value else "none"))
        else:
            rows.append((name, str(value)))
    return rows


def html_report(title: str, summary: Mapping[str, Any],
                pictures: Sequence[tuple[str, str | os.PathLike]],
                notes: Sequence[str] = ()) -> str:
    """A self-contained HTML page: the summary as a table, then the captioned pictures.

    summary: nested plain data (e.g. the demo's summary.json); pictures: (caption, PNG
    path) pairs, embedded as base64; notes: warnings or remarks shown as a list.
    """
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'>",
        f"<title>{html.escape(title)}</title>",
        "<style>body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;"
        "color:#222}table{border-collapse:collapse}td{padding:2px 12px;border-bottom:1px "
        "solid #ddd}td:last-child{text-align:right;font-variant-numeric:tabular-nums}"
        "figure{margin:2em 0}img{max-width:100%}figcaption{color:#555}</style></head><body>",
        f"<h1>{html.escape(title)}</h1><table>",
    ]
    parts += [f"<tr><td>{html.escape(k)}</td><td>{html.escape(v)}</td></tr>"
              for k, v in _rows(summary)]
    parts.append("</table>")
    if notes:
        parts.append("<h2>Notes</h2><ul>")
        parts += [f"<li>{html.escape(n)}</li>" for n in notes]
        parts.append("</ul>")
    for caption, png in pictures:
        data = base64.b64encode(Path(png).read_bytes()).decode("ascii")
        parts.append(f"<figure><img alt='{html.escape(caption)}' "
                     f"src='data:image/png;base64,{data}'>"
                     f"<figcaption>{html.escape(caption)}</figcaption></figure>")
    parts.append("</body></html>")
    return "\n".join(parts)


# --------------------------------------------------------------------------- plots


def plot_layers(stack: Stack, ks: list[int], path: Path) -> None:
    """Draw layers ``ks`` of a stack into a PNG at ``path`` (written atomically)."""
    plt = pyplot()

    n = max(1, len(ks))
    cols = min(3, n)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 4.0 * rows), squeeze=False)
    lim = None
    pts = [r for k in ks for r in stack[k].part.rings]
    if pts:
        allp = np.concatenate(pts)
        lo, hi = allp.min(axis=0), allp.max(axis=0)
        pad = 0.05 * float(max(hi - lo)) + 1.0
        lim = (lo - pad, hi + pad)
    for ax, k in zip(axes.ravel(), ks):
        layer = stack[k]
        reg = layer.part
        depth = reg.depth() if len(reg) else np.zeros(0, dtype=int)
        for ring, d in zip(reg.rings, depth):
            closed = closed_polyline(ring)
            hole = d % 2 == 1
            ax.plot(closed[:, 0], closed[:, 1], "--" if hole else "-",
                    color="tab:red" if hole else "tab:blue", lw=0.9)
            ax.fill(ring[:, 0], ring[:, 1], color="white" if hole else "tab:blue",
                    alpha=1.0 if hole else 0.15, zorder=d)
        ax.set_title(f"layer {k}: z = {layer.z:.2f} mm, {len(reg)} contours, "
                     f"{reg.area:.0f} mm²", fontsize=9)
        ax.set_aspect("equal")
        if lim is not None:
            ax.set_xlim(lim[0][0], lim[1][0])
            ax.set_ylim(lim[0][1], lim[1][1])
        ax.set_xlabel("x (mm)", fontsize=8)
        ax.set_ylabel("y (mm)", fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in axes.ravel()[len(ks):]:
        ax.axis("off")
    fig.tight_layout()
    save_figure(fig, path)


def plot_ruled(edges: RuledEdges, stack: Stack, ks: list[int], path: Path) -> None:
    """Ruled layer edges in a PNG at ``path``: for layers ``ks`` the contour (grey), the
    next layer's contour (black) and each generator's foot coloured by its tilt in plan
    view; and the tilt of every generator against height (degrees from vertical, positive
    leaning out of the material)."""
    plt = pyplot()
    n = len(ks)
    fig, axes = plt.subplots(1, n + 1, figsize=(4.2 * (n + 1), 4.2), squeeze=False)
    axes = axes.ravel()
    ok = edges.matched
    tilt = np.degrees(edges.tilt)
    lim = float(np.nanmax(np.abs(tilt))) if ok.any() else 1.0
    lim = max(lim, 1.0)
    for ax, k in zip(axes, ks):
        for ring in stack[k].part.rings:
            c = closed_polyline(ring)
            ax.plot(c[:, 0], c[:, 1], color="0.6", lw=0.8)
        if k + 1 < len(stack):
            for ring in stack[k + 1].part.rings:
                c = closed_polyline(ring)
                ax.plot(c[:, 0], c[:, 1], color="k", lw=0.5)
        sel = (edges.layer == k) & ok
        sc = ax.scatter(edges.point[sel, 0], edges.point[sel, 1], c=tilt[sel], s=4,
                        cmap="coolwarm", vmin=-lim, vmax=lim)
        ax.set_title(f"layer {k} (z = {stack[k].z:.2f} mm) to {k + 1}", fontsize=9)
        ax.set_aspect("equal")
        ax.set_xlabel("x (mm, part frame)", fontsize=8)
        ax.set_ylabel("y (mm)", fontsize=8)
        ax.tick_params(labelsize=7)
        fig.colorbar(sc, ax=ax, shrink=0.7).set_label("tilt (deg)", fontsize=8)
    ax = axes[n]
    ax.scatter(edges.z[ok], tilt[ok], s=1, color="tab:blue", alpha=0.3)
    ax.set_xlabel("z (mm)", fontsize=8)
    ax.set_ylabel("generator tilt from vertical (deg; + overhang)", fontsize=8)
    ax.set_title(f"{int(ok.sum())} generators, {int((~ok).sum())} points without",
                 fontsize=9)
    ax.tick_params(labelsize=7)
    fig.tight_layout()
    save_figure(fig, path)


def plot_toolpaths(stack: Stack, toolpaths: Toolpaths | Mapping[int, LayerPaths],
                   ks: list[int], path: Path) -> None:
    """Draw layers ``ks``: regions filled (part blue, scaffold orange), boundaries solid,
    fill thin, travel (a tour's travel curves too) dashed grey, measurement dotted green.
    PNG written atomically.
    toolpaths: the build's, or the layers ``ks`` alone by index (``icefab paths`` keeps no
    other layer's paths)."""
    layers = toolpaths if isinstance(toolpaths, Mapping) else toolpaths.layers
    plt = pyplot()
    from matplotlib.collections import LineCollection
    from matplotlib.patches import PathPatch
    from matplotlib.path import Path as MplPath

    n = max(1, len(ks))
    cols = min(2, n)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(6.0 * cols, 5.6 * rows), squeeze=False)
    for ax, k in zip(axes.ravel(), ks):
        layer = stack[k]
        for material, region in (("part", layer.part), ("scaffold", layer.scaffold)):
            if region.is_empty:
                continue
            verts, codes = [], []
            for ring in region.rings:
                verts.append(closed_polyline(ring))
                c = np.full(len(ring) + 1, MplPath.LINETO)
                c[0], c[-1] = MplPath.MOVETO, MplPath.CLOSEPOLY
                codes.append(c)
            patch = PathPatch(MplPath(np.concatenate(verts), np.concatenate(codes)),
                              facecolor=_COLOUR[material], alpha=0.18, lw=0,
                              label=f"{material} region")
            ax.add_patch(patch)
        lp = layers[k]
        # one collection per kind of line: a bunny layer holds hundreds of paths, and one
        # ax.plot each took most of the picture's time (issue 17)
        kinds: dict[tuple[str, str], list[np.ndarray]] = {}
        for p in lp.paths:
            # travel and measurement: one kind whatever the material (one legend entry)
            material = p.material if p.role in ("boundary", "fill") else ""
            if p.off is None:
                kinds.setdefault((p.role, material), []).append(p.polyline())
                continue
            # a tour: its runs as the role's lines, its travel curves as travel
            kinds.setdefault((p.role, material), []).extend(r for r, _ in p.deposited_runs())
            poly = p.polyline()
            kinds.setdefault(("travel", ""), []).extend(
                poly[a:b + 1] for a, b in true_runs(~p.segment_on()))
        for role, material in sorted(kinds, key=lambda rm: (_LINE_ORDER.get(rm[0], 0), rm[1])):
            if role == "travel":
                style = dict(colors="0.45", linewidths=0.6, linestyles="--")
            elif role == "measure":
                style = dict(colors="tab:green", linewidths=0.6, linestyles=":")
            elif role == "boundary":
                style = dict(colors=_COLOUR[material], linewidths=1.3)
            else:
                style = dict(colors=_COLOUR[material], linewidths=0.5, alpha=0.8)
            label = f"{material} {role}" if material else role
            ax.add_collection(LineCollection(kinds[(role, material)], label=label, **style))
        ax.set_title(f"layer {k}: z = {layer.z:.2f} mm, {len(lp.paths)} paths, unfilled "
                     f"{area_text(lp.unfilled_mm2[0])}/{area_text(lp.unfilled_mm2[1])} mm²",
                     fontsize=9)
        ax.set_aspect("equal")
        ax.autoscale_view()
        ax.set_xlabel("x (mm)", fontsize=8)
        ax.set_ylabel("y (mm)", fontsize=8)
        ax.tick_params(labelsize=7)
        if ax.get_legend_handles_labels()[0]:  # an empty layer has nothing to name
            ax.legend(fontsize=6, loc="upper right")
    for ax in axes.ravel()[len(ks):]:
        ax.axis("off")
    fig.tight_layout()
    save_figure(fig, path)


def plot_rms(open_loop: "SimResult", closed: "SimResult", path: Path) -> None:
    """RMS height deviation vs nominal height, open loop and SMF (thesis Fig. 5-9)."""
    plt = pyplot()

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    ax.plot(open_loop.nominal_z, open_loop.rms, "o-", color="tab:red", ms=3,
            label="open loop")
    ax.plot(closed.nominal_z, closed.rms, "s-", color="tab:blue", ms=3, label="SMF")
    ax.set_xlabel("nominal part height (mm)")
    ax.set_ylabel(r"RMS height deviation $\sigma_l^*$ (mm)")
    ax.set_title("part accuracy with and without surface mapping feedback", fontsize=10)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path)


def plot_surfaces(open_loop: "SimResult", closed: "SimResult", layer: int,
                  path: Path) -> None:
    """Height error surfaces of one measurement layer, open loop and SMF (Fig. 5-8)."""
    plt = pyplot()

    pair = [(name, res.surfaces[layer], res) for name, res in
            (("open loop", open_loop), ("SMF", closed))]
    finite = np.concatenate([s.z[np.isfinite(s.z)] for _, s, _ in pair])
    lim = float(np.percentile(np.abs(finite), 99.0)) if finite.size else 1.0
    lim = max(lim, 1e-3)
    fig, axes = plt.subplots(1, 2, figsize=(11.0, 4.8), constrained_layout=True)
    im = None
    for ax, (name, surf, res) in zip(axes, pair):
        xs, ys = surf.grid()
        g = surf.spacing
        extent = (xs[0] - g / 2, xs[-1] + g / 2, ys[0] - g / 2, ys[-1] + g / 2)
        im = ax.imshow(np.ma.masked_invalid(surf.z), origin="lower", extent=extent,
                       cmap="RdBu_r", vmin=-lim, vmax=lim, interpolation="nearest")
        i = int(np.flatnonzero(res.layers == layer)[0])
        ax.set_title(f"{name}: layer {layer}, nominal {res.nominal_z[i]:.2f} mm, "
                     rf"$\sigma_l^*$ = {res.rms[i]:.3f} mm", fontsize=9)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_aspect("equal")
    fig.colorbar(im, ax=axes, shrink=0.9, label="height - nominal (mm)")
    save_figure(fig, path)


def plot_error_response(result, dist, job, path, mode: str) -> None:
    plt = pyplot()
    n_d = job.feedback.interval_layers
    dh = job.slicing.layer_thickness_mm
    sim = simulate_1d((result.kp, result.ki, result.kd), dist, n_d=n_d, dh_d=dh)
    k = np.arange(1, len(sim.e) + 1)
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(7, 5.5), sharex=True)
    ax1.plot(k, sim.e, label="error $e_k$")
    ax1.step(k, sim.d, where="post", color="0.6", lw=1, label="disturbance $d_k$")
    ax1.axhline(0, color="k", lw=0.5)
    ax1.set_ylabel("normalised by $\\Delta h_m$")
    ax1.legend(loc="upper right")
    ax1.set_title(f"SMF 1D response, {mode}: $K_p$={result.kp:.3f}, $K_i^*$={result.ki:.3f}, "
                  f"$K_d^*$={result.kd:.3f}\n$\\sigma_p^*$={result.rms:.4g}, "
                  f"max |pole| = {result.max_pole:.3f}", fontsize=9)
    ax2.plot(k, sim.nu, color="C1")
    # a diverging response (unstable gains) would flatten everything on a linear axis:
    # keep the disturbance's scale and say how far the error runs away
    lim = 10.0 * max(float(np.max(np.abs(sim.d))) if len(sim.d) else 0.0, 0.1)
    with np.errstate(invalid="ignore"):
        away = np.flatnonzero(~(np.abs(sim.e) <= lim))
    if len(away):
        ax1.set_ylim(-lim, lim)
        last = sim.e[-1]
        ax1.text(0.02, 0.05, f"diverges: |e| > {lim:g} from layer {int(k[away[0]])}, "
                 f"{abs(last):.3g} at layer {int(k[-1])}", transform=ax1.transAxes,
                 color="C3", fontsize=9)
        nu_ok = sim.nu[:away[0]] if away[0] > 0 else sim.nu[:1]
        span = float(np.max(np.abs(nu_ok))) if len(nu_ok) else 1.0
        ax2.set_ylim(-3 * max(span, 1.0), 3 * max(span, 1.0))
    ax2.set_ylabel("valve frequency $\\nu$ (Hz)")
    ax2.set_xlabel("measurement layer k")
    fig.tight_layout()
    save_figure(fig, path)


def plot_speed(layer, path: Path, vmax: float, job: "Job | None" = None) -> None:
    """Samples of one layer's trajectories (``icefab.motion.LayerMotion``) coloured by
    speed, mm/s from 0 to ``vmax`` (thesis Fig. 4-11), PNG.

    job: when given, each trajectory is drawn where its tool is, in the part frame
    (:func:`icefab.frames.to_part_frame`), so part and scaffold paths lie on their regions;
    without it the end effector's base-frame positions are drawn and the axis label says
    that each material's paths are then offset by its nozzle's offset (about 8.5 mm for the
    Cobra 600's scaffold nozzle)."""
    plt = pyplot()
    from matplotlib.collections import LineCollection

    from icefab.frames import to_part_frame

    fig, ax = plt.subplots(figsize=(7.5, 6.5))
    segs, speeds, pts = [], [], []
    for tr in layer.trajectories:
        if len(tr.xy) < 2:
            continue
        if job is not None:
            tool = tr.path.tool_name if tr.path is not None else "part"
            tr = dataclasses.replace(tr, xy=to_part_frame(tr.xy, tool, job))
        if tr.path is not None and tr.path.role == "travel":
            ax.plot(tr.xy[:, 0], tr.xy[:, 1], color="0.75", lw=0.5, ls="--", zorder=1)
            continue
        segs.append(np.stack([tr.xy[:-1], tr.xy[1:]], axis=1))
        speeds.append(0.5 * (tr.speed[:-1] + tr.speed[1:]))
        pts.append(tr.xy)
    if segs:
        lc = LineCollection(np.concatenate(segs), cmap="viridis", linewidths=1.2, zorder=2)
        lc.set_array(np.concatenate(speeds))
        lc.set_clim(0.0, vmax)
        ax.add_collection(lc)
        allp = np.concatenate(pts)
        ax.scatter(allp[:, 0], allp[:, 1], s=0.6, c="k", zorder=3, linewidths=0)
        fig.colorbar(lc, ax=ax, label="speed (mm/s)")
        ax.autoscale()
    ax.set_aspect("equal")
    ax.set_title(f"layer {layer.index}: z = {layer.z:.2f} mm, {layer.n_points} samples, "
                 f"{layer.duration:.1f} s", fontsize=10)
    if job is not None:
        ax.set_xlabel("x, part frame: where each nozzle is (mm)")
    else:
        ax.set_xlabel("x, end effector in the robot base frame; each material's paths "
                      "shifted by its nozzle offset (mm)", fontsize=8)
    ax.set_ylabel("y (mm)")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
