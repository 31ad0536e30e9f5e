"""Export to robomimic-style HDF5 and Minari, import the HDF5 back: exact round trips.

The robomimic side is checked with a reader that follows robomimic's documented layout (robomimic
itself is not a dependency); the Minari side with ``minari.load_dataset`` in a temporary
``MINARI_DATASETS_PATH``.
"""

from __future__ import annotations

import json
import os
import sys

import h5py
import numpy as np
import pytest
from test_demonstrations import make_demo  # the synthetic demonstrations of the file tests

from gym_coffee import ENV_ID, STAGES
from gym_coffee.datasets import (
    ROBOMIMIC_ENV_TYPE,
    export_minari,
    export_robomimic,
    import_robomimic,
    obs_keys,
)
from gym_coffee.demonstrations import DemonstrationFormatError, DemonstrationSet
from gym_coffee.env import OBS_DIM, OBS_SLICES


@pytest.fixture(params=["joint", "ee"])
def demos(request) -> DemonstrationSet:
    rng = np.random.default_rng(5)
    action_type = request.param
    items = [
        make_demo(rng, n, seed=s, action_type=action_type) for n, s in ((9, 2), (4, 7), (2, 1))
    ]
    items[1].success = False
    items[0].stages[-3:] = True  # stages reached at the end
    return DemonstrationSet(items, metadata={"env_id": None, "who": "synthetic"})


def assert_same(a: DemonstrationSet, b: DemonstrationSet) -> None:
    """Equal as DemonstrationSet.__eq__ defines it (every array, dtype and value) and metadata."""
    assert a == b
    for x, y in zip(a, b, strict=True):
        for obj in x.object_pos:
            assert x.object_quat[obj].dtype == y.object_quat[obj].dtype
            np.testing.assert_array_equal(x.object_pos[obj], y.object_pos[obj])
        np.testing.assert_array_equal(x.stages, y.stages)


# -- robomimic ----------------------------------------------------------------------------------


def read_like_robomimic(path):
    """What robomimic's SequenceDataset and FileUtils read: env_args, demo keys, num_samples,
    obs/<key>, next_obs/<key>, actions, rewards, dones, mask/<filter>."""
    out = {}
    with h5py.File(path, "r") as f:
        env_meta = json.loads(f["data"].attrs["env_args"])
        demos = sorted(f["data"].keys(), key=lambda k: int(k[5:]))
        out["env_meta"] = env_meta
        out["total"] = int(f["data"].attrs["total"])
        out["demos"] = {}
        for ep in demos:
            g = f[f"data/{ep}"]
            n = int(g.attrs["num_samples"])
            out["demos"][ep] = {
                "num_samples": n,
                "obs": {k: g[f"obs/{k}"][()] for k in g["obs"]},
                "next_obs": {k: g[f"next_obs/{k}"][()] for k in g["next_obs"]},
                "actions": g["actions"][()],
                "rewards": g["rewards"][()],
                "dones": g["dones"][()],
            }
        out["masks"] = {
            k: [e.decode("utf-8") for e in np.array(f[f"mask/{k}"][:])] for k in f.get("mask", {})
        }
    return out


def test_robomimic_layout(demos, tmp_path):
    path = export_robomimic(demos, tmp_path / "d.hdf5", valid_fraction=0.34)
    data = read_like_robomimic(path)
    assert data["env_meta"]["type"] == ROBOMIMIC_ENV_TYPE == 2
    assert "env_name" in data["env_meta"] and "env_kwargs" in data["env_meta"]
    assert list(data["demos"]) == ["demo_0", "demo_1", "demo_2"]
    assert data["total"] == 8 + 3 + 1
    for demo, ep in zip(demos, data["demos"].values(), strict=True):
        n = demo.n_steps - 1
        assert ep["num_samples"] == n
        np.testing.assert_array_equal(ep["actions"], demo.actions[:-1])
        obs = np.hstack([ep["obs"][k] for k, _, _ in obs_keys(demos)])
        nxt = np.hstack([ep["next_obs"][k] for k, _, _ in obs_keys(demos)])
        np.testing.assert_array_equal(obs, demo.observations[:-1])
        np.testing.assert_array_equal(nxt, demo.observations[1:])
        assert ep["dones"].tolist() == [0] * (n - 1) + [1]
        assert ep["rewards"].tolist() == [0.0] * (n - 1) + [float(demo.success)]
    train, valid = data["masks"]["train"], data["masks"]["valid"]
    assert len(valid) == 1 and sorted(train + valid) == ["demo_0", "demo_1", "demo_2"]


def test_robomimic_round_trip_is_exact(demos, tmp_path):
    path = export_robomimic(demos, tmp_path / "d.hdf5")
    back = import_robomimic(path)
    assert_same(back, demos)
    assert back.action_type == demos.action_type
    assert sorted(os.listdir(tmp_path)) == ["d.hdf5"]  # no temporary file left


def test_robomimic_never_overwrites(demos, tmp_path):
    path = tmp_path / "d.hdf5"
    path.write_bytes(b"precious")
    with pytest.raises(FileExistsError, match="overwrite=True"):
        export_robomimic(demos, path)
    assert path.read_bytes() == b"precious"
    export_robomimic(demos, path, overwrite=True)
    assert import_robomimic(path) == demos


def test_robomimic_import_refuses_what_it_cannot_trust(demos, tmp_path):
    path = export_robomimic(demos, tmp_path / "d.hdf5")
    text = tmp_path / "t.hdf5"
    text.write_text("not hdf5")
    with pytest.raises(DemonstrationFormatError, match="is not an HDF5 file"):
        import_robomimic(text)
    with pytest.raises(DemonstrationFormatError, match="the limit is 1000"):
        import_robomimic(path, max_bytes=1000)

    def edited(name, edit):
        out = tmp_path / name
        out.write_bytes(path.read_bytes())
        with h5py.File(out, "a") as f:
            edit(f)
        with pytest.raises(DemonstrationFormatError) as info:
            import_robomimic(out)
        return str(info.value)

    def external(f):
        del f["data/demo_1/actions"]
        f["data/demo_1/actions"] = h5py.ExternalLink("/etc/passwd", "/x")

    assert "actions is an ExternalLink; links to other files or paths are not followed" in edited(
        "ext.hdf5", external
    )

    def reshape(f):
        del f["data/demo_0/gym_coffee/time"]
        f["data/demo_0/gym_coffee/time"] = np.zeros(10**6)

    assert "/data/demo_0/gym_coffee/time has shape (1000000,); expected (9,)" in edited(
        "shape.hdf5", reshape
    )

    def nan(f):
        f["data/demo_2/gym_coffee/ee_pos"][0, 0] = np.nan

    assert "'ee_pos' contains NaN" in edited("nan.hdf5", nan)

    def foreign(f):
        del f["data"].attrs["gym_coffee_metadata"]

    assert "not written by gym_coffee.datasets.export_robomimic" in edited("f.hdf5", foreign)

    def other(f):  # an HDF5 file of something else altogether
        del f["data"]
        f["x"] = np.arange(3)

    assert "has no 'data' group: not a robomimic dataset" in edited("o.hdf5", other)


def test_one_state_demonstrations_cannot_be_exported(tmp_path):
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="demonstration 0 has 1 recorded state"):
        export_robomimic(DemonstrationSet([make_demo(rng, 1)]), tmp_path / "d.hdf5")
    assert os.listdir(tmp_path) == []


def test_missing_extra_is_named(demos, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "h5py", None)
    with pytest.raises(ImportError, match=r'pip install "gym-coffee\[datasets\]"'):
        export_robomimic(demos, tmp_path / "d.hdf5")
    monkeypatch.setitem(sys.modules, "minari", None)
    with pytest.raises(ImportError, match=r"'minari'.*gym-coffee\[datasets\]"):
        export_minari(demos, "coffee/x-v0", root=tmp_path)


# -- Minari -------------------------------------------------------------------------------------


def test_minari_round_trip(demos, tmp_path, monkeypatch):
    import minari

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    folder = export_minari(demos, "coffee/synthetic-v0")
    assert folder == tmp_path / "coffee" / "synthetic-v0"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # temp folder gone
    dataset = minari.load_dataset("coffee/synthetic-v0")
    assert dataset.total_episodes == 3 and dataset.total_steps == 8 + 3 + 1
    for demo, ep in zip(demos, dataset.iterate_episodes(), strict=True):
        np.testing.assert_array_equal(ep.observations, demo.observations)
        np.testing.assert_array_equal(ep.actions, demo.actions[:-1])
        assert ep.terminations[-1] == demo.success and ep.truncations[-1] == (not demo.success)
        assert ep.rewards.sum() == float(demo.success)
        for j, name in enumerate(STAGES):
            np.testing.assert_array_equal(ep.infos["stages"][name], demo.stages[:, j])
        for obj in demo.object_pos:
            np.testing.assert_array_equal(ep.infos["object_pos"][obj], demo.object_pos[obj])
            np.testing.assert_array_equal(ep.infos["object_quat"][obj], demo.object_quat[obj])
        np.testing.assert_array_equal(ep.infos["time"], demo.time)
    with pytest.raises(FileExistsError):
        export_minari(demos, "coffee/synthetic-v0")
    export_minari(demos[:1], "coffee/synthetic-v0", overwrite=True)
    assert minari.load_dataset("coffee/synthetic-v0").total_episodes == 1
    with pytest.raises(ValueError, match="dataset_id"):
        export_minari(demos, "not a valid id!")


def test_minari_with_the_env_spec(tmp_path, monkeypatch):
    """With a registered env id the dataset can recover its environment."""
    import minari

    rng = np.random.default_rng(3)
    demos = DemonstrationSet(
        [make_demo(rng, 5, seed=1, obs_dim=OBS_DIM)],
        metadata={
            "env_id": ENV_ID,
            "env_kwargs": {"render_mode": "human"},  # never opens a GUI
            "obs_slices": {k: [v.start, v.stop] for k, v in OBS_SLICES.items()},
        },
    )
    export_minari(demos, "coffee-spec-v0", root=tmp_path)
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    dataset = minari.load_dataset("coffee-spec-v0")
    assert dataset.spec.env_spec.id == ENV_ID
    assert dataset.observation_space.shape == (OBS_DIM,)
    assert [k for k, _, _ in obs_keys(demos)] == list(OBS_SLICES)
    wrong = DemonstrationSet([make_demo(rng, 5)], metadata={"env_id": ENV_ID})
    with pytest.raises(ValueError, match="observations of 41"):
        export_minari(wrong, "coffee-wrong-v0", root=tmp_path)


def test_export_and_import_command_line(demos, tmp_path, capsys, monkeypatch):
    from lgp_policy.app.cli import main

    src = demos.save(tmp_path / "d.npz")
    h5 = tmp_path / "new" / "d.hdf5"  # outputs may go to folders that do not exist yet
    assert main(["export", str(src), "--format", "robomimic", "--out", str(h5)]) == 0
    assert main(["import", str(h5), "--out", str(tmp_path / "new2" / "back.npz")]) == 0
    assert DemonstrationSet.load(tmp_path / "new2" / "back.npz") == demos
    assert main(["export", str(src), "--format", "robomimic", "--out", str(h5)]) == 2
    assert "exists" in capsys.readouterr().err
    root = tmp_path / "m"
    minari_args = ["export", str(src), "--format", "minari", "--out", "coffee/cli-v0"]
    assert main([*minari_args, "--minari-root", str(root)]) == 0
    assert (root / "coffee" / "cli-v0").is_dir()
    assert main([*minari_args, "--minari-root", str(root)]) == 2
    assert "exists" in capsys.readouterr().err
    assert main([*minari_args, "--minari-root", str(root), "--force"]) == 0
    bad = ["export", str(src), "--format", "minari", "--out", "no good id"]
    assert main(bad) == 2 and "not a Minari dataset id" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:  # argparse: not an .hdf5 name
        main(["import", str(src), "--out", str(tmp_path / "z.npz")])
    assert exit_info.value.code == 2
