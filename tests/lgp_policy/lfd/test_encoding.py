"""Encoding of synthetic demonstrations with a known constraint (Sec. III)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from lgp_policy.lfd.encoding import DemonstrationEncoder, constraint_intervals, resample

MODELS = ["empirical", "local"]

CONSTRAINT = (0.38, 0.52)  # phase interval where the end effector sits at a fixed point of the cup


def _bump(s, a, b, edge=0.06):
    """Smooth 0 -> 1 -> 0 weight, 1 on [a, b]."""
    up = np.clip((s - (a - edge)) / edge, 0, 1)
    down = np.clip(((b + edge) - s) / edge, 0, 1)
    w = np.minimum(up, down)
    return w * w * (3 - 2 * w)


def synthetic_demos(n=4, seed=0):
    """Demos whose end effector visits cup + (0, 0, 0.05) during CONSTRAINT, free elsewhere."""
    rng = np.random.default_rng(seed)
    times, joints, ees, frames = [], [], [], []
    for _ in range(n):
        n_steps = int(rng.integers(150, 220))
        t = np.arange(n_steps) * 0.05
        s = t / t[-1]
        cup = np.array([0.5, 0.0, 0.0]) + rng.uniform(-0.15, 0.15, 3) * [1, 1, 0]
        start = rng.uniform(-0.6, 0.6, 3)
        end = rng.uniform(-0.6, 0.6, 3)
        free = (
            start
            + (end - start) * s[:, None]
            + 0.1 * np.sin(2 * np.pi * s[:, None] * rng.uniform(0.5, 1.5, 3))
        )
        w = _bump(s, *CONSTRAINT)[:, None]
        ee = (1 - w) * free + w * (cup + np.array([0.0, 0.0, 0.05]))
        ee = ee + rng.normal(0.0, 0.002, ee.shape)  # 2 mm of sensor / human jitter
        q = np.column_stack([ee, np.sin(s) + rng.normal(0, 0.01, n_steps)])  # stand-in joints
        times.append(t)
        joints.append(q)
        ees.append(ee)
        frames.append({"cup": (cup, np.eye(3))})
    return times, joints, ees, frames


def test_resample_endpoints_and_linearity():
    t = np.array([1.0, 2.0, 4.0])
    v = np.array([[0.0, 10.0], [1.0, 20.0], [3.0, 40.0]])
    r = resample(t, v, 4)
    np.testing.assert_allclose(r[0], v[0])
    np.testing.assert_allclose(r[-1], v[-1])
    np.testing.assert_allclose(r[:, 0], [0.0, 1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="increasing"):
        resample([0.0, 0.0, 1.0], v, 4)


def test_constraint_intervals_finds_the_dip():
    s = np.linspace(0, 1, 101)
    std = np.ones((101, 3))
    std[30:41] = 0.05
    (iv,) = constraint_intervals(s, std)
    assert iv[0] == pytest.approx(0.30) and iv[1] == pytest.approx(0.40)


@pytest.mark.parametrize("model", MODELS)
def test_known_constraint_shows_low_std_exactly_there(model):
    times, joints, ees, frames = synthetic_demos()
    enc = DemonstrationEncoder(n_steps=100, model=model).fit(times, joints, ees, frames)
    assert enc.frame_names_ == ["joint", "cup"]
    assert enc.data_["cup"].shape == (4, 100, 3)
    s = np.linspace(0, 1, 201)
    mean, std = enc.predict(s, "cup")
    inside = (s > CONSTRAINT[0] + 0.02) & (s < CONSTRAINT[1] - 0.02)
    outside = (s < CONSTRAINT[0] - 0.12) | (s > CONSTRAINT[1] + 0.12)
    assert std[inside].max() < 0.25 * np.median(std[outside])
    np.testing.assert_allclose(
        mean[inside], np.tile([0.0, 0.0, 0.05], (inside.sum(), 1)), atol=0.01
    )
    report = enc.constraint_report()
    cup = [r for r in report if r["frame"] == "cup"]
    assert len(cup) == 1
    assert CONSTRAINT[0] - 0.06 <= cup[0]["start"] <= CONSTRAINT[0] + 0.03
    assert CONSTRAINT[1] - 0.03 <= cup[0]["end"] <= CONSTRAINT[1] + 0.06
    assert cup[0]["label"].startswith("cup, t 0.")


def test_rotated_frame_is_learned_in_its_own_axes():
    times, joints, ees, frames = synthetic_demos(n=3, seed=1)
    rng = np.random.default_rng(2)
    rotated = []
    for f in frames:
        yaw = rng.uniform(-0.5, 0.5)
        R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
        rotated.append({"cup": f["cup"], "machine": (f["cup"][0], R)})
    enc = DemonstrationEncoder(n_steps=50, model="empirical").fit(times, joints, ees, rotated)
    for i, f in enumerate(rotated):
        o, R = f["machine"]
        back = o + enc.data_["machine"][i] @ R.T
        np.testing.assert_allclose(back, resample(times[i], ees[i], 50), atol=1e-12)


def test_input_validation():
    times, joints, ees, frames = synthetic_demos(n=2)
    with pytest.raises(ValueError, match="one of"):
        DemonstrationEncoder(model="nope").fit(times, joints, ees, frames)
    frames[1] = {"machine": frames[1]["cup"]}
    with pytest.raises(ValueError, match=r"same objects|must name"):
        DemonstrationEncoder(model="empirical").fit(times, joints, ees, frames)
    with pytest.raises(RuntimeError, match="not fitted"):
        DemonstrationEncoder().predict([0.5])


def test_landmark_alignment_puts_events_at_their_mean_phase():
    from lgp_policy.lfd.encoding import phase_of

    t = np.linspace(0.0, 10.0, 101)
    s = phase_of(t, [2.0, 6.0], [0.3, 0.5])
    assert s[0] == 0.0 and s[-1] == 1.0
    assert s[20] == pytest.approx(0.3) and s[60] == pytest.approx(0.5)
    assert np.all(np.diff(s) > 0)
    np.testing.assert_allclose(phase_of(t), t / 10.0)
    # two demonstrations whose step happens at different times line up after alignment
    t1, t2 = np.linspace(0, 1, 101), np.linspace(0, 2, 201)
    y1, y2 = (t1 > 0.3).astype(float), (t2 > 1.4).astype(float)
    enc = DemonstrationEncoder(n_steps=101, model="empirical")
    enc.fit([t1, t2], [y1[:, None], y2[:, None]], landmarks=[[0.3], [1.4]])
    assert enc.landmark_phases_ == pytest.approx([0.5])
    d = enc.data_["joint"][:, :, 0]
    assert np.abs(d[0] - d[1]).max() <= 1.0 and np.abs(d[0] - d[1]).sum() < 1.0


def test_planar_frames_match_the_spatial_encoding_of_the_same_motion():
    """2-D frames (origin (2,), rotation (2, 2), ee_pos (n, 2k)) give the first two columns of
    the 3-D encoding of the same planar motion, and wrong shapes are refused by name."""
    times, joints, ees, frames = synthetic_demos(n=3, seed=3)
    rng = np.random.default_rng(4)
    frames3, frames2, ees2 = [], [], []
    for f, ee in zip(frames, ees, strict=True):
        yaw = rng.uniform(-1.0, 1.0)
        R2 = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
        R3 = np.eye(3)
        R3[:2, :2] = R2
        o = f["cup"][0]
        frames3.append({"cup": (o, R3)})
        frames2.append({"cup": (o[:2], R2)})
        ees2.append(np.hstack([ee[:, :2], ee[:, :2] + 0.1]))  # two points on the hand
    z = [np.zeros((len(e), 1)) for e in ees2]
    ees3 = [np.hstack([e[:, :2], zi, e[:, 2:], zi]) for e, zi in zip(ees2, z, strict=True)]
    enc3 = DemonstrationEncoder(n_steps=40, model="empirical").fit(times, joints, ees3, frames3)
    enc2 = DemonstrationEncoder(n_steps=40, model="empirical").fit(times, joints, ees2, frames2)
    d3, d2 = enc3.data_["cup"], enc2.data_["cup"]
    assert d2.shape == (3, 40, 4)
    np.testing.assert_allclose(d2[:, :, :2], d3[:, :, :2], atol=1e-12)
    np.testing.assert_allclose(d2[:, :, 2:], d3[:, :, 3:5], atol=1e-12)
    m, s = enc2.predict(np.linspace(0, 1, 7), "cup")
    assert m.shape == s.shape == (7, 4)
    bad = [dict(f) for f in frames2]
    bad[1] = {"cup": (bad[1]["cup"][0], np.eye(3))}
    with pytest.raises(
        ValueError, match=r"frames\[1\]\['cup'\]: rotation must have shape \(2, 2\)"
    ):
        DemonstrationEncoder(model="empirical").fit(times, joints, ees2, bad)
    with pytest.raises(ValueError, match=r"ee_pos\[0\] must have shape \(n_steps, k \* 2\)"):
        DemonstrationEncoder(model="empirical").fit(
            times, joints, [e[:, :3] for e in ees2], frames2
        )


def test_new_demonstration_scale_is_the_t_over_gaussian_quantile_ratio():
    """The factor is t_{n-1}(q) / z(q), q = (1 + level) / 2 (values from scipy.stats), 1 for a
    single demonstration, and falls towards 1 as demonstrations are added."""
    import scipy.stats

    from lgp_policy.lfd.encoding import new_demonstration_scale

    for n in (2, 3, 4, 8, 50):
        for level in (0.9, 0.95):
            q = 0.5 * (1.0 + level)
            expected = scipy.stats.t.ppf(q, n - 1) / scipy.stats.norm.ppf(q)
            assert new_demonstration_scale(n, level) == pytest.approx(expected, rel=1e-12)
    assert new_demonstration_scale(1) == 1.0
    assert new_demonstration_scale(4) == pytest.approx(1.62, abs=0.01)
    scales = [new_demonstration_scale(n) for n in range(2, 30)]
    assert all(a > b > 1.0 for a, b in itertools.pairwise(scales))


def _sine_demos(n=4, n_samples=60, seed=0):
    """``n`` demonstrations of one sine-shaped output on their own time grids (unit scale),
    coinciding at the start and the end (spread ~0.1 in between)."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, n_samples)
    times = [rng.uniform(3.0, 6.0) * s for _ in range(n)]
    ys = [np.sin(2 * np.pi * s) + 0.1 * rng.standard_normal() * np.sin(np.pi * s) for _ in range(n)]
    return times, ys


@pytest.mark.parametrize("model", ["local", "empirical"])
def test_std_floor_is_relative_to_each_dimensions_own_scale(model):
    """Demonstrations in small units get the std of the same demonstrations in other small
    units, scaled (the floor is a fraction of each dimension's std, not 1e-4 in its units), and
    the std never exceeds the dimension's spread by much, whatever its unit."""
    times, ys = _sine_demos()
    stds = {}
    for unit in (1e-3, 1e-6, 1e-9):
        enc = DemonstrationEncoder(n_steps=50, model=model)
        enc.fit(times, [unit * y[:, None] for y in ys])
        _, std = enc.predict(np.linspace(0.0, 1.0, 41))
        data_std = np.std(enc.data_["joint"])
        assert np.all(np.isfinite(std)) and np.all(std > 0)
        assert std.max() <= 0.5 * data_std, (unit, std.max() / data_std)
        stds[unit] = std / unit
    np.testing.assert_allclose(stds[1e-6], stds[1e-3], rtol=1e-6)
    np.testing.assert_allclose(stds[1e-9], stds[1e-3], rtol=1e-6)


def test_std_floor_per_dimension_next_to_a_huge_and_a_nearly_constant_one():
    """Columns in 1e-6 units, 1e6 units and ``0.35 + 1e-9 y``: each std within 100x the
    column's own std (the floor of one column does not depend on the others)."""
    times, ys = _sine_demos(seed=1)
    joints = [np.column_stack([1e-6 * y, 1e6 * y, 0.35 + 1e-9 * y]) for y in ys]
    enc = DemonstrationEncoder(n_steps=50, model="empirical").fit(times, joints)
    _, std = enc.predict(np.linspace(0.0, 1.0, 41))
    data_std = enc.data_["joint"].reshape(-1, 3).std(axis=0)
    assert np.all(np.isfinite(std)) and np.all(std > 0)
    assert np.all(std.max(axis=0) <= 100.0 * data_std), std.max(axis=0) / data_std
    assert np.all(std.min(axis=0) <= 0.01 * data_std)  # the floor lets the coinciding ends be tight


@pytest.mark.parametrize("model", ["local", "empirical"])
@pytest.mark.parametrize("value", [0.0, 0.35, 1000.0])
def test_exactly_constant_dimension_gets_a_tiny_positive_std(model, value):
    """A dimension all demonstrations hold at one value: mean that value, std finite, > 0 and
    at the level of the values' float precision (not a floor in their units, nor growing with
    the value beyond that)."""
    times, ys = _sine_demos(n=3, seed=2)
    joints = [np.column_stack([y, np.full_like(y, value)]) for y in ys]
    enc = DemonstrationEncoder(n_steps=50, model=model).fit(times, joints)
    mean, std = enc.predict(np.linspace(0.0, 1.0, 41))
    np.testing.assert_allclose(mean[:, 1], value, rtol=1e-12, atol=1e-300)
    assert np.all(np.isfinite(std)) and np.all(std > 0)
    assert np.all(std[:, 1] <= 1e-12 * abs(value) + 1e-100), std[:, 1].max()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda t, q: ([t[0], np.r_[t[1][:-1], np.nan]], q), r"times\[1\] .*NaN"),
        (lambda t, q: ([t[0], np.r_[t[1][:3], t[1][2], t[1][4:]]], q), r"times\[1\] .*increasing"),
        (lambda t, q: ([t[0], t[1][::-1]], q), r"times\[1\] .*increasing"),
        (lambda t, q: ([t[0][:, None], t[1]], q), r"times\[0\] .*1-D.*\(60, 1\)"),
        (lambda t, q: ([t[0], t[1][:1]], [q[0], q[1][:1]]), r"times\[1\] .*at least 2"),
        (lambda t, q: ([t[0], ["a"] * 60], q), r"times\[1\] .*numbers"),
        (lambda t, q: ([], []), r"times .*at least one"),
        (lambda t, q: (t, [q[0], np.r_[q[1][:-1], [[np.nan]]]]), r"joint_pos\[1\] .*NaN"),
        (
            lambda t, q: (t, [q[0], np.c_[q[1], q[1]]]),
            r"joint_pos\[1\] .*2 columns.*joint_pos\[0\]",
        ),
        (lambda t, q: (t, [q[0][:, :0], q[1][:, :0]]), r"joint_pos\[0\] .*no columns"),
        (lambda t, q: (t, [q[0], q[1][:-1]]), r"joint_pos\[1\] .*59 rows.*times\[1\]"),
        (lambda t, q: (t, [q[0], q[1][:, :, None]]), r"joint_pos\[1\] .*shape"),
        (lambda t, q: (t, q[:1]), r"joint_pos .*2"),
    ],
)
def test_fit_names_the_bad_argument(change, message):
    times, ys = _sine_demos(n=2)
    t, q = change(times, [y[:, None] for y in ys])
    with pytest.raises(ValueError, match=message):
        DemonstrationEncoder(model="empirical").fit(t, q)


def test_fit_names_bad_frames_ee_pos_and_landmarks():
    times, joints, ees, frames = synthetic_demos(n=2)
    fit = DemonstrationEncoder(model="empirical").fit
    bad_ee = [ees[0], np.r_[ees[1][:-1], [[np.nan] * 3]]]
    with pytest.raises(ValueError, match=r"ee_pos\[1\] .*NaN"):
        fit(times, joints, bad_ee, frames)
    with pytest.raises(ValueError, match=r"ee_pos\[0\] .*rows.*times\[0\]"):
        fit(times, joints, [ees[0][:-1], ees[1]], frames)
    with pytest.raises(ValueError, match=r"ee_pos .*frames"):
        fit(times, joints, None, frames)
    with pytest.raises(ValueError, match=r"frames\[1\]\['cup'\] .*pair"):
        fit(times, joints, ees, [frames[0], {"cup": frames[1]["cup"][0]}])
    with pytest.raises(ValueError, match=r"frames\[1\]\['cup'\]: origin .*finite"):
        fit(times, joints, ees, [frames[0], {"cup": (np.full(3, np.nan), np.eye(3))}])
    with pytest.raises(ValueError, match=r"frames\[0\] .*'joint'.*reserved"):
        fit(times, joints, ees, [{**f, "joint": f["cup"]} for f in frames])
    mid = [t[len(t) // 2] for t in times]
    with pytest.raises(ValueError, match=r"landmarks\[1\] .*NaN"):
        fit(times, joints, ees, frames, landmarks=[[mid[0]], [np.nan]])
    with pytest.raises(ValueError, match=r"landmarks\[1\] .*inside"):
        fit(times, joints, ees, frames, landmarks=[[mid[0]], [times[1][-1] + 1.0]])
    with pytest.raises(ValueError, match=r"landmarks\[1\] .*1 .*landmarks\[0\] .*2"):
        fit(times, joints, ees, frames, landmarks=[[mid[0], mid[0] + 0.1], [mid[1]]])


def test_predict_names_the_bad_argument():
    times, ys = _sine_demos(n=2)
    enc = DemonstrationEncoder(n_steps=20, model="empirical").fit(times, [y[:, None] for y in ys])
    with pytest.raises(ValueError, match=r"phase .*NaN"):
        enc.predict([0.1, np.nan])
    with pytest.raises(ValueError, match=r"phase .*numbers"):
        enc.predict(["x"])
    with pytest.raises(ValueError, match=r"phase .*1-D"):
        enc.predict(np.zeros((3, 2)))
    with pytest.raises(ValueError, match=r"frame must be one of \['joint'\], got 'cup'"):
        enc.predict([0.5], "cup")
    with pytest.raises(KeyError):  # still a KeyError for callers that catch one
        enc.predict([0.5], "cup")
