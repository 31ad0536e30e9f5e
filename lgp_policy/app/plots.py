"""Figures in the style of the paper: Fig. 1 (heteroscedastic fit), Fig. 2 (input-space clustering),
Fig. 4 (constraint profile per frame), Fig. 5 (a reproduction on a new layout).

matplotlib is imported lazily; the figures are made without pyplot (nothing global changes) and
drawn by Agg. Each PNG is written atomically and an existing file is replaced only with
``force=True`` (``FileExistsError`` otherwise, before any drawing).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lgp_policy._io import atomic_output, check_output_path
from lgp_policy.lfd.encoding import JOINT_FRAME

__all__ = [
    "make_all",
    "plot_clustering",
    "plot_constraint_profile",
    "plot_heteroscedastic",
    "plot_reproduction",
    "rollout_trace",
    "trace_from_episode",
]

AXES = ("x", "y", "z")
FRAME_COLORS = {"cup": "tab:blue", "machine": "tab:green", JOINT_FRAME: "tab:gray"}
MODEL_LABELS = {
    "local": "local heteroscedastic",
    "heteroscedastic": "global heteroscedastic",
    "exact": "standard",
    "empirical": "empirical",
}
STAGE_LABELS = {"cup_grasped": "grasp", "cup_placed": "place", "button_pressed": "press"}


def _figure(**kwargs: Any) -> Any:
    """A matplotlib ``Figure`` made without pyplot: nothing global changes (no backend switch,
    no figure kept by pyplot), and pyplot is not imported (~0.2 CPU s); PNGs are drawn by Agg."""
    from matplotlib.figure import Figure

    return Figure(**kwargs)


def _cmap(name: str) -> Any:
    import matplotlib

    return matplotlib.colormaps[name]


def _check_png(path: str | Path, force: bool) -> Path:
    """A figure's path, checked before any drawing (a ``.png`` name; an existing file only with
    ``force``)."""
    return check_output_path(path, force=force, suffixes=(".png",), what="figure")


def _save(fig: Any, path: str | Path, force: bool) -> Path:
    """Save a figure (PNG, 110 dpi) atomically."""
    path = Path(path)
    with atomic_output(path, force=force) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    return path


def _stage_lines(ax: Any, policy: Any) -> None:
    phases = policy.constraints_.get("stage_phases", {}) if hasattr(policy, "constraints_") else {}
    for stage, s in phases.items():
        if s is None or stage not in STAGE_LABELS:  # the task stages only (no gripper events)
            continue
        ax.axvline(s, color="k", ls=":", lw=0.8)
        ax.text(
            s,
            1.0,
            STAGE_LABELS.get(stage, stage),
            transform=ax.get_xaxis_transform(),
            ha="center",
            va="bottom",
            fontsize=7,
        )


def plot_constraint_profile(
    policy: Any, path: str | Path, *, n_std: float = 2.0, force: bool = False
) -> Path:
    """Fig. 4: per object frame and axis, the demonstrations, the GP mean and a +-2 std band over
    normalised time; tight intervals (the constraint report) are shaded and labelled, demonstrated
    stage times are dotted lines."""
    path = _check_png(path, force)
    frames = [n for n in policy.frame_names_ if n != JOINT_FRAME]
    if not frames:
        frames = [JOINT_FRAME]
    s = policy.phase_grid_
    data = getattr(getattr(policy, "encoder_", None), "data_", None)
    fig = _figure(figsize=(4.2 * len(frames), 7.0))
    axes = fig.subplots(3, len(frames), sharex=True, squeeze=False)
    intervals = policy.constraints_.get("intervals", [])
    for c, name in enumerate(frames):
        color = FRAME_COLORS.get(name, "tab:red")
        for r in range(3):
            ax = axes[r, c]
            if data is not None and name in data:
                demo_s = np.linspace(0.0, 1.0, data[name].shape[1])
                for k, demo in enumerate(data[name]):
                    ax.plot(
                        demo_s,
                        demo[:, r],
                        color="k",
                        lw=0.7,
                        alpha=0.6,
                        label="demonstrations" if k == 0 else None,
                    )
            m, sd = policy.mean_[name][:, r], policy.std_[name][:, r]
            ax.fill_between(
                s, m - n_std * sd, m + n_std * sd, color=color, alpha=0.25, label=f"+-{n_std:g} std"
            )
            ax.plot(s, m, color=color, lw=2.0, label="GP mean")
            for iv in intervals:
                if iv["frame"] == name:
                    ax.axvspan(
                        iv["start"],
                        iv["end"],
                        color="orange",
                        alpha=0.25,
                        lw=0,
                        label="tight" if r == 0 and iv is intervals[0] else None,
                    )
            if r == 0:
                _stage_lines(ax, policy)
                labels = [iv["label"] for iv in intervals if iv["frame"] == name]
                ax.set_title(
                    f"relative to {name}\n"
                    + (
                        "tight: " + "; ".join(lab.split(", ", 1)[1] for lab in labels)
                        if labels
                        else "no tight interval"
                    ),
                    fontsize=9,
                    pad=12,
                )
            ax.set_ylabel(f"{AXES[r]} (m)")
            ax.grid(alpha=0.3)
        axes[-1, c].set_xlabel("normalised time")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.suptitle(
        "Learned policies relative to the objects' initial poses (cf. Fig. 4)", fontsize=10
    )
    fig.tight_layout(rect=(0, 0.04, 1, 0.97))
    return _save(fig, path, force)


def trace_from_episode(policy: Any, episode: Any) -> dict[str, Any]:
    """What Fig. 5 needs, computed after the fact from an episode rolled out with
    ``keep_observations=True``: ``policy.predict_distribution`` replayed on the episode's
    observations, in order, from a fresh start (the policy is deterministic, so the replay
    takes the very actions of the roll-out; this is checked).

    Returns:
        ``{"phase" (n,), "ee_pos" (n, 3), "joint_pos" (n, 7), "joint_std" (n, 7),
        "targets": {frame: (n, 3) world targets}, "reached": {stage: bool}}`` for the ``n``
        observations the policy acted on.
    """
    import inspect

    from gym_coffee.env import obs_part
    from lgp_policy.lfd.reproduction import frame_estimate

    if episode.observations is None:
        raise ValueError("the episode has no observations (roll it out with keep_observations)")
    obs = np.asarray(episode.observations, dtype=float)[:-1]  # the last one was not acted on
    if "episode_start" in inspect.signature(policy.predict_distribution).parameters:
        # a policy with memory (online frame filter, event-driven phase): replay step by step
        steps = [
            policy.predict_distribution(o, episode_start=np.array([i == 0]))
            for i, o in enumerate(obs)
        ]
        phase = np.concatenate([d.phase for d in steps]).astype(float)
        joint_std = np.concatenate([d.joint_std for d in steps]).astype(float)
        actions = np.concatenate([d.action for d in steps])
    else:
        dist = policy.predict_distribution(obs)
        phase, joint_std = np.asarray(dist.phase, float), np.asarray(dist.joint_std, float)
        actions = np.asarray(dist.action)
    if episode.actions is not None and not np.allclose(actions, episode.actions, atol=1e-6):
        raise RuntimeError("replaying the policy on the episode gave other actions")
    # the frames as the policy reads them (its adapter), at the first observation
    read = policy.adapter_.read(obs[:1])
    frames = {name: (pos[0], rot[0]) for name, (pos, rot) in read.frames.items()}
    targets = {}
    for n in policy.frame_names_:
        if n not in frames:
            continue
        # the grasp point (the first 3 of the frame's task vector) at each phase
        m = np.stack(
            [np.interp(phase, policy.phase_grid_, col) for col in policy.mean_[n][:, :3].T], axis=1
        )
        o, R = frames[n]
        targets[n] = np.stack([frame_estimate(o, R, mi, np.ones(3)).position for mi in m])
    return {
        "phase": phase,
        "ee_pos": np.stack([obs_part(o, "ee_pos") for o in obs]).astype(float),
        "joint_pos": np.stack([obs_part(o, "joint_pos") for o in obs]).astype(float),
        "joint_std": joint_std,
        "targets": targets,
        "reached": {k: bool(episode.reached.get(k, False)) for k in STAGE_LABELS},
    }


def rollout_trace(policy: Any, seed: int, *, env_factory: Any = None) -> dict[str, Any]:
    """Roll ``policy`` out on ``reset(seed=seed)`` (the one episode loop) and return
    :func:`trace_from_episode`. ``env_factory`` defaults to ``gym_coffee.ENV_ID``."""
    import gymnasium as gym

    import gym_coffee
    from lgp_policy.rollout import run_episode

    env = env_factory() if env_factory is not None else gym.make(gym_coffee.ENV_ID)
    try:
        episode = run_episode(policy, env, seed, flags=tuple(STAGE_LABELS), keep_observations=True)
    finally:
        env.close()
    return trace_from_episode(policy, episode)


def plot_reproduction(policy: Any, trace: dict, path: str | Path, *, force: bool = False) -> Path:
    """Fig. 5: (a) task space, the targets of each object frame (dotted/dashed) and the resulting
    end-effector path (solid red); (b) joint space, the reproduced joints with the remaining
    +-2 std of the fused estimate and the joint-space GP mean."""
    path = _check_png(path, force)
    fig = _figure(figsize=(12, 6.5))
    grid = fig.add_gridspec(3, 2, width_ratios=(1.0, 1.1))
    task_axes = [fig.add_subplot(grid[r, 0]) for r in range(3)]
    s = trace["phase"]
    styles = {"cup": ":", "machine": "--"}
    for r, axis in enumerate(AXES):
        ax = task_axes[r]
        for n, tgt in trace["targets"].items():
            ax.plot(
                s,
                tgt[:, r],
                ls=styles.get(n, "-."),
                color=FRAME_COLORS.get(n, "tab:purple"),
                lw=1.4,
                label=f"policy rel. to {n}",
            )
        ax.plot(s, trace["ee_pos"][:, r], color="tab:red", lw=2, label="resulting policy")
        ax.set_ylabel(f"{axis} (m)")
        ax.grid(alpha=0.3)
        if r == 0:
            _stage_lines(ax, policy)
            ax.set_title("(a) reproduction in task space (world frame)", fontsize=10, pad=14)
            ax.legend(fontsize=7, loc="best")
        if r < 2:
            ax.tick_params(labelbottom=False)
    task_axes[-1].set_xlabel("normalised time")
    ax = fig.add_subplot(grid[:, 1])
    q, qs = trace["joint_pos"], trace["joint_std"]
    colors = _cmap("tab10")
    for j in range(q.shape[1]):
        ax.fill_between(
            s, q[:, j] - 2 * qs[:, j], q[:, j] + 2 * qs[:, j], color=colors(j), alpha=0.2
        )
        ax.plot(s, q[:, j], color=colors(j), lw=1.5, label=f"q{j + 1}")
        ax.plot(
            policy.phase_grid_, policy.mean_[JOINT_FRAME][:, j], color=colors(j), lw=0.8, ls="--"
        )
    ax.set_xlabel("normalised time")
    ax.set_ylabel("joint position (rad)")
    ax.set_title("(b) reproduction in joint space (dashed: joint-space GP mean)", fontsize=10)
    ax.legend(fontsize=7, ncol=4, loc="best")
    ax.grid(alpha=0.3)
    reached = trace.get("reached", {})
    flags = ", ".join(f"{v} {'yes' if reached.get(k) else 'no'}" for k, v in STAGE_LABELS.items())
    fig.suptitle(f"Reproduction on a new layout (cf. Fig. 5): {flags}", fontsize=10)
    fig.tight_layout()
    return _save(fig, path, force)


def _pick_dimension(encoder: Any) -> tuple[str, int]:
    """The object-frame dimension whose spread varies most over time (clearly heteroscedastic)."""
    best, best_ratio = (encoder.frame_names_[0], 0), -1.0
    for name in encoder.frame_names_:
        if name == JOINT_FRAME and len(encoder.frame_names_) > 1:
            continue
        spread = encoder.data_[name][:, :, :3].std(axis=0)  # (T, 3): the grasp point
        ratio = (spread.max(axis=0) + 1e-6) / (np.median(spread, axis=0) + 1e-6)
        j = int(np.argmax(ratio))
        if ratio[j] > best_ratio:
            best, best_ratio = (name, j), float(ratio[j])
    return best


def _xy(encoder: Any, name: str, j: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    Y = encoder.data_[name][:, :, j]
    return np.tile(encoder.phase_, Y.shape[0])[:, None], Y.reshape(-1)


def plot_heteroscedastic(
    encoder: Any,
    path: str | Path,
    *,
    frame: str | None = None,
    dim: int | None = None,
    force: bool = False,
) -> Path:
    """Fig. 1 on one dimension of the demonstrations: (a) a standard (homoscedastic) GP, (b) the
    encoder's own model (the local heteroscedastic GP the policy uses; +-2 std includes the
    input-dependent noise), (c) the noise models against the demonstrations' spread."""
    path = _check_png(path, force)
    from lgp_policy.gp.exact import GaussianProcess
    from lgp_policy.gp.heteroscedastic import HeteroscedasticGP

    if frame is None or dim is None:
        frame, dim = _pick_dimension(encoder)
    X, y = _xy(encoder, frame, dim)
    xs = np.linspace(0.0, 1.0, 300)[:, None]
    gp = GaussianProcess(encoder.make_kernel(), random_state=0).fit(X, y)
    used = encoder.models_[frame][dim]
    hgp = HeteroscedasticGP(encoder.make_kernel(), random_state=0).fit(X, y)
    fig = _figure(figsize=(13, 3.8))
    axes = fig.subplots(1, 3)
    label = f"{frame} {AXES[dim] if frame != JOINT_FRAME else f'dim {dim}'}"
    demos = encoder.data_[frame][:, :, dim]
    for ax, model, title in (
        (axes[0], gp, "(a) standard GP"),
        (axes[1], used, f"(b) {MODEL_LABELS.get(encoder.model, encoder.model)} GP (used)"),
    ):
        m, sd = model.predict(xs, return_std=True)
        for k in range(demos.shape[0]):
            ax.plot(encoder.phase_, demos[k], color="k", lw=0.7)
        ax.fill_between(xs[:, 0], m - 2 * sd, m + 2 * sd, color="tab:blue", alpha=0.25)
        ax.plot(xs[:, 0], m, color="tab:blue", lw=2)
        ax.set_title(f"{title}: {label}", fontsize=10)
        ax.set_xlabel("normalised time")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("m")
    ax = axes[2]
    if hasattr(used, "noise_variance"):
        ax.plot(
            xs[:, 0],
            np.sqrt(used.noise_variance(xs)),
            color="tab:orange",
            lw=2,
            label=f"sqrt r(x), {MODEL_LABELS.get(encoder.model, encoder.model)} (used)",
        )
    ax.plot(
        xs[:, 0],
        np.sqrt(hgp.noise_variance(xs)),
        color="tab:purple",
        lw=1.2,
        ls="-.",
        label="sqrt r(x), one global heteroscedastic GP",
    )
    ax.plot(
        xs[:, 0],
        np.sqrt(gp.noise_variance(xs)),
        color="tab:gray",
        ls="--",
        label="noise std, standard GP",
    )
    ddof = 1 if demos.shape[0] > 1 else 0
    ax.plot(
        encoder.phase_,
        demos.std(axis=0, ddof=ddof),
        color="k",
        lw=0.8,
        label="spread of the demonstrations",
    )
    ax.set_title("(c) noise models", fontsize=10)
    ax.set_xlabel("normalised time")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.suptitle("Standard vs heteroscedastic GP on the demonstrations (cf. Fig. 1)", fontsize=10)
    fig.tight_layout()
    return _save(fig, path, force)


def plot_clustering(
    encoder: Any,
    path: str | Path,
    *,
    frame: str | None = None,
    dim: int | None = None,
    threshold: float | None = None,
    force: bool = False,
) -> Path:
    """Fig. 2: the input-space clustering of a ``LocalGP`` (Algorithm 1): data coloured by local
    model, the centres (squares) and the weighting functions ``k(x, c_l)``."""
    path = _check_png(path, force)
    from lgp_policy.gp.local import LocalGP

    if frame is None or dim is None:
        frame, dim = _pick_dimension(encoder)
    model = encoder.models_[frame][dim]
    if not hasattr(model, "centers_"):
        X, y = _xy(encoder, frame, dim)
        model = LocalGP(encoder.make_kernel(), threshold=threshold or encoder.threshold).fit(X, y)
    X = np.asarray(model.X_train_ if hasattr(model, "X_train_") else _xy(encoder, frame, dim)[0])
    y = np.asarray(model.y_train_ if hasattr(model, "y_train_") else _xy(encoder, frame, dim)[1])
    X = X.reshape(len(X), -1)[:, 0]
    y = y.reshape(len(y), -1)[:, 0]
    assign = np.asarray(model.assignments_)
    centers = np.asarray(model.centers_).reshape(-1)
    ls = getattr(encoder, "length_scale", 0.1)
    fig = _figure(figsize=(8, 4))
    ax = fig.subplots()
    cmap = _cmap("tab10")
    markers = "os^Dv<>ph*"
    lo, hi = float(y.min()), float(y.max())
    base = lo - 0.35 * (hi - lo + 1e-9)
    xs = np.linspace(0.0, 1.0, 400)
    for k in range(len(centers)):
        sel = assign == k
        ax.scatter(
            X[sel],
            y[sel],
            s=6,
            color=cmap(k % 10),
            marker=markers[k % len(markers)],
            label=f"model {k + 1} ({sel.sum()} pts)",
        )
        w = np.exp(-0.5 * ((xs - centers[k]) / ls) ** 2)
        ax.plot(xs, base + w * 0.3 * (hi - lo + 1e-9), color=cmap(k % 10), lw=1)
        ax.scatter([centers[k]], [base], marker="s", s=40, color=cmap(k % 10), edgecolor="k")
    ax.set_xlabel("normalised time")
    ax.set_ylabel(f"{frame} {AXES[dim] if frame != JOINT_FRAME else dim} (m)")
    ax.set_title(f"Input-space clustering, {len(centers)} local models (cf. Fig. 2)", fontsize=10)
    ax.legend(fontsize=7, ncol=3, loc="upper left", markerscale=2)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return _save(fig, path, force)


def make_all(
    policy: Any,
    out: str | Path,
    *,
    seed: int | None = None,
    episode: Any = None,
    force: bool = False,
) -> dict[str, str]:
    """Write all four figures into ``out``; returns ``{name: path}``.

    Fig. 5 uses ``episode`` (an :class:`~lgp_policy.rollout.Episode` with observations, e.g. the
    first evaluation layout's) when given, else a roll-out on ``reset(seed=seed)``. Existing
    figures are replaced only with ``force`` (checked for all four before any work).
    """
    out = Path(out)
    if episode is None and seed is None:
        raise ValueError("make_all needs the episode to plot or the seed of one")
    encoder = getattr(policy, "encoder_", None)
    names = ["fig4_constraints", "fig5_reproduction"]
    if encoder is not None:
        names += ["fig2_clustering", "fig1_heteroscedastic"]
    paths = {n: _check_png(out / f"{n}.png", force) for n in names}
    files = {
        "fig4_constraints": str(
            plot_constraint_profile(policy, paths["fig4_constraints"], force=force)
        )
    }
    if episode is not None:
        trace = trace_from_episode(policy, episode)
    else:
        trace = rollout_trace(policy, int(seed))  # type: ignore[arg-type]
    files["fig5_reproduction"] = str(
        plot_reproduction(policy, trace, paths["fig5_reproduction"], force=force)
    )
    if encoder is not None:
        files["fig2_clustering"] = str(
            plot_clustering(encoder, paths["fig2_clustering"], force=force)
        )
        files["fig1_heteroscedastic"] = str(
            plot_heteroscedastic(encoder, paths["fig1_heteroscedastic"], force=force)
        )
    return files
