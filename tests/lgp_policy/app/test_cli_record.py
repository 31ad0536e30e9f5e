"""``gym-coffee record``: records real teacher demonstrations, refuses to overwrite, has help."""

from __future__ import annotations

import shutil
import subprocess
import sys

import imageio.v3 as iio
import numpy as np
import pytest

from gym_coffee.demonstrations import DemonstrationSet
from lgp_policy.app import cli
from lgp_policy.app.cli import main


def test_help(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--help"])
    assert info.value.code == 0
    assert "record" in capsys.readouterr().out
    with pytest.raises(SystemExit) as info:
        main(["record", "--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    for option in ("--n", "--out", "--seed", "--force", "--video"):
        assert option in out


def test_console_script_help():
    exe = shutil.which("gym-coffee")
    cmd = [exe, "--help"] if exe else [sys.executable, "-m", "lgp_policy.app.cli", "--help"]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert "record" in result.stdout


@pytest.mark.parametrize("bad", ["0", "-3", "two"])
def test_bad_n_is_a_usage_error(bad, tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main(["record", "--n", bad, "--out", str(tmp_path / "d.npz")])
    assert info.value.code == 2
    assert "--n" in capsys.readouterr().err
    assert not (tmp_path / "d.npz").exists()


def test_bad_video_suffix_fails_before_recording(tmp_path, capsys):
    code = main(["record", "--n", "1", "--out", str(tmp_path / "d.npz"), "--video", "x.avi"])
    assert code == 2
    assert ".mp4" in capsys.readouterr().err
    assert not (tmp_path / "d.npz").exists()


def test_record_refuses_to_overwrite(tmp_path, capsys):
    out = tmp_path / "demos.npz"
    out.write_bytes(b"keep me")
    assert main(["record", "--n", "1", "--out", str(out), "--no-progress"]) == 2
    assert "--force" in capsys.readouterr().err
    assert out.read_bytes() == b"keep me"


def test_record_one_demo_with_video_then_force(tmp_path, capsys, monkeypatch):
    # The headless renderer takes ~0.15 s a frame: a short video keeps this test fast; the full
    # video path runs in benchmarks/teacher.py --video.
    monkeypatch.setattr(cli, "VIDEO_MAX_FRAMES", 6)
    out, video = tmp_path / "data" / "demos.npz", tmp_path / "demo.gif"  # data/: a new folder
    args = ["record", "--n", "1", "--seed", "3", "--out", str(out), "--no-progress"]
    assert main([*args, "--video", str(video)]) == 0
    printed = capsys.readouterr().out
    assert "saved 1 demonstrations" in printed
    demos = DemonstrationSet.load(out)
    assert len(demos) == 1
    demo = demos[0]
    assert demo.success and demo.stages[-1].all()
    assert demo.seed >= 3 and demos.metadata["seeds"] == [demo.seed]
    assert demos.metadata["env_id"] == "gym_coffee/CoffeeTask-v0"
    assert demo.time[0] == 0.0 and np.all(np.diff(demo.time) > 0)
    frames = iio.imread(video, index=None)
    assert frames.shape[0] == 6 and frames.shape[-1] == 3 and frames.std() > 5

    # --force replaces the file; the same seed gives the same demonstration (deterministic).
    assert main([*args, "--force"]) == 0
    assert DemonstrationSet.load(out) == demos


@pytest.mark.parametrize("suffix", [".mp4", ".gif"])
def test_write_video_formats(tmp_path, suffix):
    """The video helper behind --video: odd frame sizes, both formats, read back."""
    from gym_coffee.video import write_video

    frames = [np.full((31, 45, 3), 8 * i, dtype=np.uint8) for i in range(12)]
    path = write_video(tmp_path / f"v{suffix}", frames, fps=12)
    video = iio.imread(path, index=None)
    assert video.shape[0] == 12 and video.shape[-1] == 3
    assert video.shape[1:3] in ((31, 45), (32, 46))  # H.264 pads to even sizes
    assert abs(float(video[5].mean()) - 40) < 3
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"v{suffix}"]  # no temp file left
    with pytest.raises(FileExistsError):
        write_video(path, frames, overwrite=False)


@pytest.mark.parametrize(("fps", "ms"), [(25 / 3, 120), (12.5, 80), (20, 50), (30, 30)])
def test_gif_frames_last_the_frame_period_to_the_centisecond(tmp_path, fps, ms):
    """GIF durations are centiseconds; Pillow truncates, so 1000 / (25 / 3) = 119.99.. ms gave
    110 ms frames (``gym-coffee run``'s video ran 9% fast) before it was rounded."""
    from PIL import Image

    from gym_coffee.video import write_video

    frames = [np.full((8, 8, 3), 40 * i, dtype=np.uint8) for i in range(3)]
    path = write_video(tmp_path / "v.gif", frames, fps=fps)
    with Image.open(path) as gif:
        assert gif.info["duration"] == ms


def test_write_video_errors(tmp_path):
    from gym_coffee.video import write_video

    with pytest.raises(ValueError, match=r"\.mp4"):
        write_video(tmp_path / "v.avi", [np.zeros((4, 4, 3), np.uint8)])
    with pytest.raises(ValueError, match="no frames"):
        write_video(tmp_path / "v.gif", [])
    with pytest.raises(ValueError, match="frame 1"):
        write_video(tmp_path / "v.gif", [np.zeros((4, 4, 3)), np.zeros((4, 5, 3))])
