"""``ermrl video``: a real MP4 of HalfCheetah-v5 from a trained tiny res-ppo model, headless.

Without a working OpenGL backend the test skips with the reason, except under
``ERMRL_REQUIRE_SERVICES=1`` (CI), where it fails: CI installs Mesa with
scripts/install_system_deps.sh.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests._analysis_data import TinyStudy, build_tiny_study

pytestmark = pytest.mark.slow

STEPS = 40


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> TinyStudy:
    return build_tiny_study(tmp_path_factory.getbasetemp())


def require_gl() -> str:
    """The GL backend that works here, probed in subprocesses (never in the pytest process)."""
    from ermrl.analysis import _video

    failures = []
    for backend in ("egl", "osmesa"):
        ok, why = _video._probe(backend, timeout=120)
        if ok:
            return backend
        failures.append(f"{backend}: {why}")
    message = "no OpenGL backend renders offscreen here (" + "; ".join(failures) + ")"
    if os.environ.get("ERMRL_REQUIRE_SERVICES") == "1":
        pytest.fail(message + "; run scripts/install_system_deps.sh")
    pytest.skip(message + "; install Mesa with scripts/install_system_deps.sh")


def test_video_cli_writes_a_playable_mp4_of_halfcheetah(tiny: TinyStudy, tmp_path: Path) -> None:
    import imageio.v2 as imageio

    backend = require_gl()
    out = tmp_path / "cheetah.mp4"
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "ermrl",
            "video",
            "--run",
            str(tiny.runs),
            "--agent",
            "res-ppo",
            "--seed",
            "10",
            "--max-steps",
            str(STEPS),
            "--fast",
            "--gif",
            "--out",
            str(out),
        ],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert f"GL backend {backend}" in proc.stdout
    reader = imageio.get_reader(str(out))
    meta = reader.get_meta_data()
    frames = [frame for frame in reader]
    reader.close()
    assert meta["codec"] == "h264" and meta["fps"] == pytest.approx(20.0)
    assert len(frames) == STEPS
    assert frames[0].shape == (480, 480, 3)
    # A real render, not a blank frame: the checkered floor and the cheetah show contrast.
    assert frames[-1].std() > 10
    gif = imageio.mimread(str(out.with_suffix(".gif")))
    assert len(gif) == STEPS // 2 and gif[0].shape[:2] == (240, 240)


@pytest.mark.parametrize("where", ["read-only", "full"])
def test_video_into_a_folder_that_cannot_take_it(
    tiny: TinyStudy, tmp_path: Path, where: str
) -> None:
    """A read-only folder or a full disk (real tmpfs mounts: root ignores chmod): one line on
    stderr, exit 2, and no partial MP4 or temporary file left."""
    from tests.test_bad_input import _fill, _tmpfs

    require_gl()
    options = ("ro",) if where == "read-only" else ("size=64k",)
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    with _tmpfs(tmp_path / "mnt", *options) as folder:
        if where == "full":
            _fill(folder)
        before = sorted(p.name for p in folder.iterdir())
        out = folder / "cheetah.mp4"
        proc = subprocess.run(
            [sys.executable, "-m", "ermrl", "video", "--run", str(tiny.runs), "--agent",
             "res-ppo", "--seed", "10", "--max-steps", str(STEPS), "--fast", "--out", str(out)],
            cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert proc.returncode == 2, proc.stdout + proc.stderr
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
        reason = "Read-only file system" if where == "read-only" else "No space left on device"
        assert reason in lines[0]
        assert sorted(p.name for p in folder.iterdir()) == before


@pytest.mark.parametrize(
    ("size", "extra"),
    [("64k", []), ("160k", ["--gif"])],
    ids=["mp4", "gif"],
)
def test_video_on_a_disk_that_fills_up_while_writing(
    tiny: TinyStudy, tmp_path: Path, size: str, extra: list[str]
) -> None:
    """The disk fills up inside the MP4 (ffmpeg then exits without an error reaching ermrl, and
    the MP4 had no index: it printed "wrote" with exit 0) or inside the GIF (a PluginV3.__del__
    traceback): one line, exit 2, nothing left. A real tmpfs smaller than the 100-frame video
    (about 75 kB of MP4, 150 kB of GIF) and with room for the MP4 alone."""
    from tests.test_bad_input import _tmpfs

    require_gl()
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    with _tmpfs(tmp_path / "mnt", f"size={size}") as folder:
        out = folder / "cheetah.mp4"
        proc = subprocess.run(
            [sys.executable, "-m", "ermrl", "video", "--run", str(tiny.runs), "--agent",
             "res-ppo", "--seed", "10", "--max-steps", "100", "--out", str(out), *extra],
            cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert proc.returncode == 2, proc.stdout + proc.stderr
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and "No space left on device" in lines[0], proc.stderr
        assert list(folder.iterdir()) == []
