"""Figures of the paper: ratio-of-exploration curves (Figure 3) and top-down trajectories of several
models on the same episode (Figure 4), a failure case (Figure 5), and an optional egocentric GIF;
beside Table 1, validation success against training frames and minutes, and the training episodes' success
and policy entropy."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from mapless.evaluate.metrics import EpisodeResult, exploration_curve
from mapless.sim.config import SimConfig
from mapless.sim.library import SceneLibrary

#: Distinct colours for up to 14 lines (the medium ablation has 13 rows with its cvmeta), so that no
#: two rows of a figure are told apart by line style alone; past them, styles change.
MODEL_COLOURS = (
    "tab:red",
    "tab:blue",
    "tab:green",
    "tab:purple",
    "tab:orange",
    "tab:brown",
    "tab:pink",
    "tab:olive",
    "tab:cyan",
    "tab:gray",
    "black",
    "gold",
    "navy",
    "lime",
)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")  # files only; never needs a display
    import matplotlib.pyplot as plt

    return plt


def exploration_figure(
    results: Mapping[str, Sequence[EpisodeResult]], path: Path, horizon: int = 100, min_episodes: int = 10
) -> dict[str, list[float]]:
    """Figure 3: mean ratio of exploration against the step index, one curve per model.

    A curve stops where fewer than ``min_episodes`` episodes are still running (its mean would be
    noise). Returns the plotted curves (NaN beyond the cut) for the JSON report.
    """
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    curves = {}
    for i, (label, res) in enumerate(results.items()):
        mean, count = exploration_curve(res, horizon)
        mean = np.where(count >= min_episodes, mean, np.nan)
        steps = np.arange(1, len(mean) + 1)
        ax.plot(steps, 100 * mean, label=label, color=MODEL_COLOURS[i % len(MODEL_COLOURS)])
        curves[label] = [None if np.isnan(v) else float(v) for v in mean]
    ax.set_xlabel("step")
    ax.set_ylabel("ratio of exploration (%)")
    ax.set_ylim(0, 105)
    ax.set_title("Ratio of exploration (distinct states / steps)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return curves


def model_style(i: int) -> tuple[str, str]:
    """Colour and line format of the ``i``-th model of a figure: the palette's colours solid, then
    again dashed with square markers (an ablation has more rows than the palette has colours)."""
    colour = MODEL_COLOURS[i % len(MODEL_COLOURS)]
    return colour, ("o-", "s--", "^:")[(i // len(MODEL_COLOURS)) % 3]


def _two_panels(labels: set[str], sharey: bool = False):
    """A figure of two panels side by side with room below them for a legend of many or long
    ``labels`` (inside an axes they squeeze it); returns ``(plt, fig, axes, legend_rows)``."""
    plt = _pyplot()
    below = len(labels) > 4 or max(len(label) for label in labels) > 40
    legend_rows = (len(labels) + 1) // 2 if below else 0
    fig, axes = plt.subplots(1, 2, figsize=(11, 4 + 0.3 * legend_rows), sharey=sharey)
    return plt, fig, axes, legend_rows


def _legend_and_save(plt, fig, axes, legend_rows: int, path: Path) -> None:
    if not legend_rows:
        axes[0].legend()
        fig.tight_layout()
    else:
        handles, labels = axes[0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="lower center", ncol=2, fontsize="small", frameon=False)
        fig.tight_layout(rect=(0, 0.3 * legend_rows / (4 + 0.3 * legend_rows) + 0.02, 1, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    # A long row label in the two-column legend is wider than half the figure: the tight box keeps it.
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)


def validation_figure(selections: Mapping[str, Sequence[Mapping]], path: Path) -> bool:
    """Validation SR at every snapshot a selection scored, against training frames (left) and
    training minutes (right): one colour per model, one line per seed, the chosen snapshot ringed.

    ``selections``: model -> per seed, its selection as the reports keep it
    (:meth:`~mapless.evaluate.selection.Selection.summary`: ``chosen``, and ``candidates`` with
    ``path``, ``success``, ``frames`` and ``minutes``, None when the run's log did not reach it).
    Returns False, and writes nothing, when no candidate knows its frames (records made before
    snapshots kept them).
    """
    seeds = [
        (i, label, sel["chosen"], [c for c in sel["candidates"] if c.get("frames", -1) >= 0])
        for i, (label, per_seed) in enumerate(selections.items())
        for sel in per_seed
    ]
    if not any(points for *_, points in seeds):
        return False
    plt, fig, axes, legend_rows = _two_panels({label for _, label, _, _ in seeds}, sharey=True)
    labelled = set()  # one legend entry per model, however many seeds
    for i, label, chosen, points in seeds:
        colour, line = model_style(i)
        for ax, key, scale in ((axes[0], "frames", 1e-3), (axes[1], "minutes", 1.0)):
            kept = [
                (c[key] * scale, 100 * c["success"], c["path"] == chosen)
                for c in points
                if c.get(key) is not None
            ]
            ax.plot([x for x, _, _ in kept], [y for _, y, _ in kept], line, color=colour, markersize=3.5,
                    label=None if label in labelled else label)  # fmt: skip
            for x, y, _ in filter(lambda point: point[2], kept):  # the selected snapshot, ringed
                ax.plot(x, y, "o", markersize=11, markerfacecolor="none", markeredgecolor=colour)
        labelled.add(label)
    axes[0].set_xlabel("training frames (thousands)")
    axes[1].set_xlabel("training minutes")
    axes[0].set_ylabel("validation SR (%)")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.set_ylim(bottom=0)
    fig.suptitle("Validation success at every snapshot (ringed: the one selected and reported)")
    _legend_and_save(plt, fig, axes, legend_rows, path)
    return True


def training_figure(curves: Mapping[str, Sequence[Mapping]], path: Path) -> bool:
    """What the training episodes said as a run trained, against its training frames: the share of
    them ended by a successful Done (left) and the policy's mean entropy per step (right); one colour
    per model, one line per seed.

    ``curves``: model -> per seed, its training log as the reports keep it (``frames``, ``success``
    and ``entropy`` lists, one entry per logged interval). Returns False, and writes nothing, when
    no seed has a record.
    """
    seeds = [
        (i, label, c) for i, (label, per_seed) in enumerate(curves.items()) for c in per_seed if c["frames"]
    ]
    if not seeds:
        return False
    plt, fig, axes, legend_rows = _two_panels({label for _, label, _ in seeds})
    labelled = set()
    for i, label, curve in seeds:
        colour, line = model_style(i)
        thousands = [f * 1e-3 for f in curve["frames"]]
        axes[0].plot(thousands, [100 * s for s in curve["success"]], line[1:] or "-", color=colour,
                     label=None if label in labelled else label)  # fmt: skip
        axes[1].plot(thousands, curve["entropy"], line[1:] or "-", color=colour)
        labelled.add(label)
    axes[0].set_ylabel("training success (%)")
    axes[1].set_ylabel("policy entropy (nats per step)")
    for ax in axes:
        ax.set_xlabel("training frames (thousands)")
        ax.grid(alpha=0.3)
        ax.set_ylim(bottom=0)
    fig.suptitle("The training episodes: success and policy entropy at every logged interval")
    _legend_and_save(plt, fig, axes, legend_rows, path)
    return True


def _path_xy(library: SceneLibrary, result: EpisodeResult) -> np.ndarray:
    data = library[result.scene]
    poses = np.array((result.start_pose, *result.poses), dtype=np.int64)
    return np.stack([data.x[poses], data.z[poses]], axis=1)


def trajectory_figure(
    results: Mapping[str, EpisodeResult],
    library: SceneLibrary,
    path: Path,
    sim: SimConfig | None = None,
    parents: Sequence[str] = (),
    title: str | None = None,
) -> None:
    """Figures 4/5: one top-down panel per model on the same episode: the target and its parents
    highlighted, the path from start (circle) to end (square: Done; cross: time out), the final view
    cone; the panel title says success or failure, length and optimal length."""
    from mapless.scenes.layout import load_scene
    from mapless.sim.pictures import draw_top_down

    plt = _pyplot()
    sim = sim or SimConfig()
    first = next(iter(results.values()))
    scene = load_scene(first.scene)
    data = library[first.scene]
    n = len(results)
    # Shared limits: every panel shows the room at the same scale, whatever its view cone covers.
    fig, axes = plt.subplots(1, n, figsize=(5.2 * n, 5.2), squeeze=False, sharex=True, sharey=True)
    for i, (ax, (label, result)) in enumerate(zip(axes[0], results.items(), strict=True)):
        if result.scene != first.scene or result.index != first.index:
            raise ValueError("trajectory_figure compares models on one and the same episode")
        end = result.poses[-1] if result.poses else result.start_pose
        end_pose = data.pose_tuple(end)
        draw_top_down(ax, scene, sim, highlight_types=(result.target, *parents), pose=end_pose)
        xy = _path_xy(library, result)
        colour = MODEL_COLOURS[i % len(MODEL_COLOURS)]
        ax.plot(xy[:, 0], xy[:, 1], "-", color=colour, linewidth=2.2, alpha=0.85, zorder=6)
        ax.plot(*xy[0], "o", color="white", markeredgecolor="black", markersize=9, zorder=7)
        ax.plot(
            *xy[-1],
            "s" if result.called_done else "X",
            color=colour,
            markeredgecolor="black",
            markersize=10,
            zorder=7,
        )
        outcome = "success" if result.success else ("wrong Done" if result.called_done else "time out")
        ax.set_title(f"{label}: {outcome}\nL = {result.length}, L* = {result.optimal_length}", fontsize=10)
    fig.suptitle(title or f"{first.scene}: find {first.target} (parents: {', '.join(parents) or 'none'})")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def trajectory_gif(
    result: EpisodeResult,
    library: SceneLibrary,
    path: Path,
    sim: SimConfig | None = None,
    size: int = 126,
) -> None:
    """Egocentric semantic views along a trajectory, one frame a step, as an animated GIF (Pillow)."""
    from PIL import Image

    from mapless.scenes.layout import load_scene
    from mapless.sim.pictures import egocentric_view

    sim = sim or SimConfig()
    scene = load_scene(result.scene)
    data = library[result.scene]
    poses = (result.start_pose, *result.poses)
    frames = [Image.fromarray(egocentric_view(scene, sim, *data.pose_tuple(p), size)) for p in poses]
    path.parent.mkdir(parents=True, exist_ok=True)
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=250, loop=0)


def pick_showcase(
    results: Mapping[str, Sequence[EpisodeResult]], focus: str
) -> tuple[int | None, int | None]:
    """Episode indices for Figure 4 (``focus`` succeeds where most other models fail, shortest
    L*-normalised path among those) and Figure 5 (a ``focus`` failure that timed out, else any)."""
    by_index = {label: {r.index: r for r in res} for label, res in results.items()}
    mine = by_index[focus]
    others = [m for label, m in by_index.items() if label != focus]

    def others_failed(i: int) -> int:
        return sum(1 for m in others if i in m and not m[i].success)

    wins = [r for r in mine.values() if r.success]
    showcase = None
    if wins:
        best = max(
            wins, key=lambda r: (others_failed(r.index), r.optimal_length / max(r.length, 1), -r.index)
        )
        showcase = best.index
    failures = [r for r in mine.values() if not r.success]
    failure = None
    if failures:
        timed_out = [r for r in failures if not r.called_done] or failures
        failure = min(timed_out, key=lambda r: r.index).index
    return showcase, failure


def steps_gif(
    result: EpisodeResult,
    library: SceneLibrary,
    path: Path,
    sim: SimConfig | None = None,
    label: str = "",
    seconds_per_step: float = 0.4,
) -> int:
    """One episode step by step as an animated GIF: the room from above with the target highlighted,
    the path so far, the agent and its view cone (green while a target instance is visible under the
    success rule), the sightings (poses that saw the target, starred) and, on the last frame, how it
    ended (Done, wrong Done, time out); beside it, the agent's egocentric view. Returns the frames
    written (the start and one per action)."""
    from matplotlib.patches import Polygon
    from PIL import Image

    from mapless.actions import ACTIONS
    from mapless.scenes.layout import load_scene
    from mapless.sim.pictures import draw_top_down, egocentric_view

    plt = _pyplot()
    sim = sim or SimConfig()
    scene = load_scene(result.scene)
    data = library[result.scene]
    poses = (result.start_pose, *result.poses)
    sees_target = data.goal_mask(result.target)[list(poses)]
    xy = _path_xy(library, result)
    fig, (top, ego) = plt.subplots(1, 2, figsize=(8.4, 4.4), gridspec_kw={"width_ratios": (1.25, 1)})
    # The room is drawn once; each frame moves only the agent's artists over it.
    draw_top_down(top, scene, sim, highlight_types=(result.target,))
    top.set_title(f"{label + ': ' if label else ''}{result.scene}, find {result.target}", fontsize=9)
    (trail,) = top.plot([], [], "-", color="tab:red", linewidth=2, alpha=0.8, zorder=6)
    (seen,) = top.plot([], [], "*", color="limegreen", markeredgecolor="black", markersize=12, zorder=7)
    (agent,) = top.plot([], [], "o", color="tab:red", markeredgecolor="black", markersize=8, zorder=8)
    cone = Polygon(np.zeros((3, 2)), closed=True, alpha=0.35, zorder=5)
    top.add_patch(cone)
    top.plot(*xy[0], "o", color="white", markeredgecolor="black", markersize=8, zorder=7)
    view = ego.imshow(egocentric_view(scene, sim, *data.pose_tuple(poses[0]), size=168))
    ego.axis("off")
    half, reach = np.radians(sim.horizontal_fov / 2), sim.visibility_distance
    frames = []
    for step, pose in enumerate(poses):
        x, z, yaw, horizon = data.pose_tuple(pose)
        angles = np.radians(yaw) + np.array([-half, half])
        cone.set_xy([[x, z], *zip(x + reach * np.sin(angles), z + reach * np.cos(angles), strict=True)])
        cone.set_color("limegreen" if sees_target[step] else "orange")
        trail.set_data(xy[: step + 1, 0], xy[: step + 1, 1])
        sighted = np.flatnonzero(sees_target[: step + 1])
        seen.set_data(xy[sighted, 0], xy[sighted, 1])
        agent.set_data([x], [z])
        view.set_data(egocentric_view(scene, sim, x, z, yaw, horizon, size=168))
        action = ACTIONS[result.actions[step - 1]] if step and step <= len(result.actions) else "start"
        text = f"step {step}/{len(poses) - 1}: {action}"
        if step == len(poses) - 1:
            outcome = "success" if result.success else ("wrong Done" if result.called_done else "time out")
            text += f"  ->  {outcome} (L = {result.length}, L* = {result.optimal_length})"
            agent.set_marker("s" if result.called_done else "X")
            agent.set_markersize(11)
        ego.set_title(text + ("\ntarget in view" if sees_target[step] else "\n"), fontsize=9)
        fig.canvas.draw()
        frames.append(Image.fromarray(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()))
    plt.close(fig)
    path.parent.mkdir(parents=True, exist_ok=True)
    # The last frame (how it ended) stays up longer.
    durations = [int(1000 * seconds_per_step)] * (len(frames) - 1) + [2500]
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=durations, loop=0)
    return len(frames)
