"""The residual policy file: round trips, and every malformed or hostile file gives one clear
error before anything is built (bounded memory, no pickles, nothing written, no sidecars)."""

from __future__ import annotations

import hashlib
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
from residual_helpers import PendulumPD, make_pendulum

pytest.importorskip("stable_baselines3")

from lgp_policy._io import FileFormatError
from lgp_policy.residual import (
    PhaseGate,
    ResidualPolicy,
    ResidualPolicyFormatError,
    finetune,
    load_any_policy,
)

SMALL = {
    "sac": {"buffer_size": 50, "batch_size": 8},
    "td3": {"buffer_size": 50, "batch_size": 8},
    "ppo": {"n_steps": 16, "batch_size": 8},
}


def _save_small_policy(folder: Path, algo: str = "td3") -> tuple[Path, ResidualPolicy]:
    result = finetune(
        PendulumPD(),
        make_pendulum,
        algo=algo,
        total_env_steps=20,
        gate=PhaseGate(start=0.0),
        progress=False,
        hyperparameters=SMALL[algo],
    )
    path = folder / f"{algo}.npz"
    result.policy.save(path)
    return path, result.policy


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    return _save_small_policy(tmp_path_factory.mktemp("small"))


@pytest.mark.parametrize("algo", ["td3", "ppo"])
def test_round_trip_other_algorithms(tmp_path, algo):
    path, policy = _save_small_policy(tmp_path, algo)
    loaded = ResidualPolicy.load(path, base=PendulumPD())
    obs = np.stack([make_pendulum().observation_space.sample() for _ in range(8)])
    np.testing.assert_array_equal(
        loaded.predict(obs, deterministic=True)[0], policy.predict(obs, deterministic=True)[0]
    )
    with np.load(path, allow_pickle=False) as data:  # nothing pickled
        assert all(data[k].dtype != object for k in data.files)


def _rewrite(src: Path, dst: Path, edit) -> Path:
    with np.load(src, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    edit(arrays)
    np.savez(dst, **arrays)
    return dst


def _set_meta(**changes):
    def edit(arrays):
        meta = json.loads(str(arrays["metadata"]))
        for key, value in changes.items():
            if key == "net_arch":
                meta["hyperparameters"]["policy_kwargs"]["net_arch"] = value
            elif key == "buffer_size":
                meta["hyperparameters"]["buffer_size"] = value
            else:
                meta[key] = value
        arrays["metadata"] = np.array(json.dumps(meta))

    return edit


def _param(arrays, ndim=2):
    return next(k for k in arrays if k.startswith("param/") and arrays[k].ndim == ndim)


def _drop_weight(arrays):
    del arrays[_param(arrays)]


def _bad_shape(arrays):
    key = _param(arrays)
    arrays[key] = arrays[key][:, :-1]


def _nan_weight(arrays):
    key = _param(arrays)
    arrays[key] = np.full_like(arrays[key], np.nan)


def _pickled_member(arrays):
    arrays["space/obs_low"] = np.array([{"a": 1}], dtype=object)


CASES = {
    "kind": (_set_meta(kind="something_else"), "kind"),
    "version": (_set_meta(schema_version=99), "schema version 99"),
    "algo": (_set_meta(algo="dqn"), "algo"),
    "scale negative": (_set_meta(scale=-1.0), "scale"),
    "scale huge": (_set_meta(scale=1e308), "scale"),
    "scale nan": (_set_meta(scale=float("nan")), "not a number|scale"),
    "obs_dim": (_set_meta(obs_dim=10**9), "obs_dim"),
    "residual_dims": (_set_meta(residual_dims=[0, 0]), "residual_dims"),
    "gate start": (_set_meta(gate={"type": "phase", "start": 5.0}), "start"),
    "gate nan": (_set_meta(gate={"type": "phase", "start": float("nan")}), "not a number"),
    "net_arch large": (_set_meta(net_arch=[2048, 2048]), "does not match the stored weights"),
    "net_arch huge": (_set_meta(net_arch=[8000, 8000]), r"net_arch\['pi'\] must be at most"),
    "buffer": (_set_meta(buffer_size=10**12), "buffer_size"),
    "base path": (_set_meta(base={"embedded": False, "path": "/etc/passwd"}), "base"),
    "missing weight": (_drop_weight, "missing"),
    "shape": (_bad_shape, "shape"),
    "nan weight": (_nan_weight, "NaN"),
    "no metadata": (lambda a: a.pop("metadata"), "metadata"),
    "no space": (lambda a: a.pop("space/act_low"), "space/act_low"),
    "pickled member": (_pickled_member, "Python objects"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_malformed_files_give_one_clear_error_before_building(tmp_path, small, case, monkeypatch):
    import lgp_policy.residual.policy as policy_module

    def no_build(*args, **kwargs):
        raise AssertionError("a network was built from an invalid file")

    path, _ = small
    edit, message = CASES[case]
    bad = _rewrite(path, tmp_path / "bad.npz", edit)
    if case not in ("missing weight", "shape"):  # those are found against the built model
        monkeypatch.setattr(policy_module, "build_model", no_build)
    with pytest.raises(ResidualPolicyFormatError, match=message):
        ResidualPolicy.load(bad, base=PendulumPD())


def test_truncated_text_and_missing_files(tmp_path, small):
    path, _ = small
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(path.read_bytes()[:200])
    text = tmp_path / "notes.npz"
    text.write_text("just some text\n")
    for bad in (truncated, text):
        with pytest.raises(ResidualPolicyFormatError, match=r"not an? (readable )?\.npz") as info:
            ResidualPolicy.load(bad, base=PendulumPD())
        assert "allow_pickle" not in str(info.value)
    with pytest.raises(FileNotFoundError):
        ResidualPolicy.load(tmp_path / "nope.npz")
    with pytest.raises(ResidualPolicyFormatError, match="without its base"):
        ResidualPolicy.load(path)  # saved without a base file


def test_unknown_members_are_never_read(tmp_path, small):
    path, policy = small
    extra = _rewrite(path, tmp_path / "extra.npz", lambda a: a.update(extra=np.zeros(3)))
    loaded = ResidualPolicy.load(extra, base=PendulumPD())
    obs = np.stack([make_pendulum().observation_space.sample() for _ in range(4)])
    np.testing.assert_array_equal(
        loaded.predict(obs, deterministic=True)[0], policy.predict(obs, deterministic=True)[0]
    )


def test_decompression_bomb_is_refused_from_the_zip_directory(tmp_path, small):
    """A member declaring more than the limit is refused before it is decompressed."""
    path, _ = small
    bomb = tmp_path / "bomb.npz"
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as dst:
        for info in src.infolist():
            dst.writestr(info.filename, src.read(info.filename))
        header = np.lib.format.header_data_from_array_1_0(np.zeros(0, np.float32))
        header["shape"] = (20 * 2**20,)  # 80 MB of float32 zeros, ~80 kB compressed
        with dst.open("param/bomb.npy", "w", force_zip64=True) as f:
            np.lib.format.write_array_header_1_0(f, header)
            chunk = bytes(2**20)
            for _ in range(80):
                f.write(chunk)
    assert bomb.stat().st_size < 2**20
    with pytest.raises(ResidualPolicyFormatError, match=r"declares \d+ bytes"):
        ResidualPolicy.load(bomb, base=PendulumPD())


def test_embedded_base_is_never_written_and_names_are_ignored(tmp_path, small):
    """A crafted embedded base naming a path outside the folder: nothing is written, one error."""
    path, _ = small
    target = tmp_path / "outside" / "bashrc"
    payload = b"echo pwned\n"
    for name in (str(target), "../../outside/bashrc"):

        def edit(arrays, name=name):
            meta = json.loads(str(arrays["metadata"]))
            meta["base"] = {
                "embedded": True,
                "name": name,
                "path": name,
                "sha256": hashlib.sha256(payload).hexdigest(),
            }
            arrays["metadata"] = np.array(json.dumps(meta))
            arrays["base_file"] = np.frombuffer(payload, dtype=np.uint8)

        evil = _rewrite(path, tmp_path / "evil.npz", edit)
        before = sorted(p.name for p in tmp_path.rglob("*"))
        with pytest.raises(ResidualPolicyFormatError, match="embedded base policy"):
            ResidualPolicy.load(evil)
        assert not target.exists()
        assert sorted(p.name for p in tmp_path.rglob("*")) == before


def test_load_any_policy_dispatches_on_kind_and_reads_no_sidecar(tmp_path, small):
    path, _ = small
    with pytest.raises(ResidualPolicyFormatError, match="without its base"):
        load_any_policy(path)  # reached ResidualPolicy.load
    bare = tmp_path / "bare.npz"
    np.savez(bare, weights=np.zeros(3))
    (tmp_path / "bare.npz.json").write_text(json.dumps({"kind": "lgp_policy.residual_policy"}))
    (tmp_path / "bare.json").write_text(json.dumps({"kind": "lgp_policy.residual_policy"}))
    # which kind of policy it is cannot be read: the common error, not a residual policy's
    with pytest.raises(FileFormatError, match="missing member 'metadata'") as info:
        load_any_policy(bare)
    assert not isinstance(info.value, ResidualPolicyFormatError)
    with pytest.raises(FileNotFoundError):
        load_any_policy(tmp_path / "nope.npz")
