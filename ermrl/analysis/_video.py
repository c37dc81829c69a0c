"""Episode videos of trained agents, rendered headless on the CPU.

MuJoCo renders offscreen through an OpenGL backend chosen by the ``MUJOCO_GL`` environment
variable, which must be set before OpenGL is first loaded in the process. Without a display,
two backends work from Debian's Mesa packages:

- ``egl``: EGL with Mesa's software (llvmpipe) driver (``libegl1``, ``libegl-mesa0``,
  ``libgl1-mesa-dri``);
- ``osmesa``: off-screen Mesa (``libosmesa6``).

[`select_gl_backend`][ermrl.analysis.select_gl_backend] tries each candidate with a tiny render in a
subprocess (a failed GL initialization can abort a process) and keeps the first that works; ``glfw``
is a candidate only when a display is available. Videos are written as MP4 (H.264, through the
``ffmpeg`` binary that the ``imageio-ffmpeg`` wheel ships) and, optionally or when MP4 fails, as
GIF.
"""

from __future__ import annotations

import errno
import os
import subprocess
import sys
import textwrap
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ermrl._io import staged_folder

__all__ = [
    "GL_BACKENDS",
    "GLBackendError",
    "VideoResult",
    "record_video",
    "select_gl_backend",
    "write_gif",
    "write_mp4",
]

GL_BACKENDS: tuple[str, ...] = ("egl", "osmesa", "glfw")
INSTALL_HINT = (
    "install Mesa's headless GL: `apt-get install -y libegl1 libegl-mesa0 libgl1-mesa-dri` (EGL) "
    "or `apt-get install -y libosmesa6` (OSMesa), e.g. with scripts/install_system_deps.sh"
)
_PROBE = textwrap.dedent(
    """
    import mujoco
    model = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><light pos='0 0 2'/><geom size='0.2'/></worldbody></mujoco>"
    )
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    renderer = mujoco.Renderer(model, 32, 32)
    renderer.update_scene(data)
    pixels = renderer.render()
    assert pixels.shape == (32, 32, 3), pixels.shape
    renderer.close()
    print("ok")
    """
)
_selected: str | None = None


class GLBackendError(RuntimeError):
    """No OpenGL backend can render offscreen here."""


@dataclass(frozen=True)
class VideoResult:
    """What [`record_video`][ermrl.analysis.record_video] wrote.

    Attributes:
        paths: The written files (MP4 and/or GIF).
        n_frames: Frames in the video.
        fps: Playback frame rate (real time: ``1 / dt`` of the env).
        size: ``(height, width)`` of the frames in pixels.
        episode_return: Return of the recorded episode.
        backend: The GL backend used (``None`` for envs that render without OpenGL).
    """

    paths: tuple[Path, ...]
    n_frames: int
    fps: float
    size: tuple[int, int]
    episode_return: float
    backend: str | None


def _display_available() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _probe(backend: str, timeout: float) -> tuple[bool, str]:
    env = dict(os.environ)
    env["MUJOCO_GL"] = backend
    if backend in ("egl", "osmesa"):
        env["PYOPENGL_PLATFORM"] = backend
    else:
        env.pop("PYOPENGL_PLATFORM", None)
    try:
        proc = subprocess.run(
            [sys.executable, "-c", _PROBE],
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
        )
    except subprocess.TimeoutExpired:
        return False, f"timed out after {timeout:.0f}s"
    if proc.returncode == 0 and "ok" in proc.stdout:
        return True, "ok"
    lines = [line for line in (proc.stderr or proc.stdout).strip().splitlines() if line.strip()]
    return False, lines[-1] if lines else f"exit code {proc.returncode}"


def _opengl_loaded() -> bool:
    return (
        "OpenGL.GL" in sys.modules or "mujoco.egl" in sys.modules or "mujoco.osmesa" in sys.modules
    )


def select_gl_backend(
    preferred: str | None = None,
    *,
    candidates: Sequence[str] | None = None,
    timeout: float = 60.0,
) -> str:
    """Pick an OpenGL backend that renders offscreen here and set ``MUJOCO_GL`` for it.

    Order: ``preferred`` alone when given; otherwise an existing ``MUJOCO_GL``, then ``egl``,
    ``osmesa`` and, with a display, ``glfw``. The choice is cached for the process. When OpenGL
    is already loaded in this process, the backend it was loaded for is kept.

    Args:
        preferred: Only try this backend (``egl``, ``osmesa`` or ``glfw``).
        candidates: Backends to try, in order (overrides the default order).
        timeout: Seconds allowed per probe.

    Returns:
        The backend, also exported as ``MUJOCO_GL`` (and ``PYOPENGL_PLATFORM`` for EGL/OSMesa).

    Raises:
        GLBackendError: none works; the message lists what was tried, why each failed, and the
            packages to install.
        ValueError: ``preferred`` is not a known backend.
    """
    global _selected
    if preferred is not None and preferred not in GL_BACKENDS:
        raise ValueError(f"unknown GL backend {preferred!r}; choose one of {GL_BACKENDS}")
    if _selected is not None and preferred in (None, _selected):
        return _selected
    if _opengl_loaded() and os.environ.get("MUJOCO_GL"):
        current = os.environ["MUJOCO_GL"]
        if preferred not in (None, current):
            raise GLBackendError(
                f"OpenGL is already loaded for MUJOCO_GL={current!r} in this process; start a "
                f"new process to use {preferred!r}"
            )
        _selected = current
        return current
    if preferred is not None:
        order = [preferred]
    elif candidates is not None:
        order = list(candidates)
    else:
        order = []
        if os.environ.get("MUJOCO_GL") in GL_BACKENDS:
            order.append(os.environ["MUJOCO_GL"])
        order += ["egl", "osmesa"] + (["glfw"] if _display_available() else [])
        order = list(dict.fromkeys(order))
    failures = []
    for backend in order:
        ok, why = _probe(backend, timeout)
        if ok:
            os.environ["MUJOCO_GL"] = backend
            if backend in ("egl", "osmesa"):
                os.environ["PYOPENGL_PLATFORM"] = backend
            else:
                os.environ.pop("PYOPENGL_PLATFORM", None)
            _selected = backend
            return backend
        failures.append(f"{backend}: {why}")
    skipped = "" if _display_available() or preferred else " (glfw skipped: no display)"
    raise GLBackendError(
        "no OpenGL backend can render MuJoCo offscreen here; tried "
        + "; ".join(failures)
        + skipped
        + ". Fix: "
        + INSTALL_HINT
    )


def _needs_gl(env_id: str) -> bool:
    import gymnasium

    spec = gymnasium.spec(env_id)
    entry = spec.entry_point if isinstance(spec.entry_point, str) else ""
    return "mujoco" in entry


def write_mp4(frames: Sequence[np.ndarray], path: str | Path, fps: float) -> Path:
    """Write RGB frames as an H.264 MP4 (yuv420p, plays in browsers and players).

    Args:
        frames: Frames of shape ``(height, width, 3)``, dtype ``uint8``.
        path: Output file.
        fps: Frames per second.

    Raises:
        RuntimeError: ``imageio-ffmpeg`` (which ships the ffmpeg binary) is missing.
    """
    import imageio.v2 as imageio

    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError as err:
        raise RuntimeError("MP4 needs imageio-ffmpeg: pip install imageio-ffmpeg") from err
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = imageio.get_writer(
        str(path),
        format="FFMPEG",
        mode="I",
        fps=fps,
        codec="libx264",
        pixelformat="yuv420p",
        quality=8,
        macro_block_size=16,
        ffmpeg_log_level="quiet",  # its errors reach us as the exception below
    )
    try:
        try:
            for frame in frames:
                writer.append_data(np.asarray(frame, dtype=np.uint8))
        finally:
            writer.close()
    except OSError as err:
        raise _write_failure(err, path) from None
    # ffmpeg that runs out of space may exit without an error reaching us, leaving a file cut
    # short: an MP4 whose index (the moov box, written last) is missing plays nowhere.
    if not _complete_mp4(path):
        raise _write_failure(OSError(errno.EIO, os.strerror(errno.EIO), str(path)), path)
    return path


def _complete_mp4(path: Path) -> bool:
    """Whether ``path`` is an MP4 with its header (``ftyp``) and its index (``moov``)."""
    try:
        if not path.is_file():  # a device (/dev/full) is never read to its end
            return False
        data = path.read_bytes()
    except OSError:
        return False
    return data[4:8] == b"ftyp" and b"moov" in data


def _write_failure(err: OSError, path: Path) -> OSError:
    """The cause of an ffmpeg write failure as a one-line ``OSError`` naming ``path``.

    ffmpeg dies and its pipe breaks (``EPIPE``, with the ffmpeg command and log in the message)
    whether the disk is full or the folder read-only: tell which from the folder itself.
    """
    import errno
    import shutil

    code = err.errno or errno.EIO
    try:
        if shutil.disk_usage(path.parent).free < 1 << 20:
            code = errno.ENOSPC
        elif not os.access(path.parent, os.W_OK):
            code = errno.EROFS
    except OSError:
        pass
    return OSError(code, os.strerror(code), str(path))


def write_gif(
    frames: Sequence[np.ndarray], path: str | Path, fps: float, *, scale: int = 2, stride: int = 2
) -> Path:
    """Write RGB frames as a looping GIF, subsampled to keep the file small.

    Args:
        frames: Frames of shape ``(height, width, 3)``, dtype ``uint8``.
        path: Output file.
        fps: Frame rate of ``frames`` (the GIF keeps real time).
        scale: Keep every ``scale``-th pixel in each direction.
        stride: Keep every ``stride``-th frame.
    """
    import imageio.v3 as iio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    picked = [np.asarray(f, dtype=np.uint8)[::scale, ::scale] for f in frames[::stride]]
    # Encoded in memory, then written in one go: a full disk is then one OSError here, not an
    # error inside the image plugin (raised again by its __del__ as a stray traceback).
    data = iio.imwrite(
        "<bytes>", np.stack(picked), extension=".gif", duration=1000.0 * stride / fps, loop=0
    )
    try:
        path.write_bytes(data)
    except OSError as err:
        if path.is_file() and not path.is_symlink():  # what was written of it (never a device)
            path.unlink(missing_ok=True)
        raise _write_failure(err, path) from None
    return path


def record_video(
    run: str | Path,
    agent: str = "res-ppo",
    seed: int | None = None,
    out: str | Path | None = None,
    *,
    max_steps: int | None = None,
    gif: bool = False,
    deterministic: bool = True,
    env_seed: int | None = None,
    gl: str | None = None,
    fast: bool = False,
) -> VideoResult:
    """Render one episode of a trained agent of a test-phase folder to MP4 (and GIF).

    Args:
        run: The test-phase folder (``--out`` of ``ermrl test``).
        agent: Agent name.
        seed: The run's seed (default: the smallest seed with a saved model).
        out: MP4 path (default ``<run>/videos/<agent>_seed<seed>.mp4``); the GIF goes next
            to it with the ``.gif`` suffix.
        max_steps: Stop after this many steps (default: the whole episode).
        gif: Also write a GIF. When the MP4 cannot be written, a GIF is written instead.
        deterministic: Use the policy's mean action.
        env_seed: Seed of the episode (default: the run's evaluation seed).
        gl: Force a GL backend (default: [`select_gl_backend`][ermrl.analysis.select_gl_backend]
            picks one).
        fast: No shadows or reflections (about 5x faster with Mesa's software renderer).

    Returns:
        The written files and the video's properties.

    Raises:
        GLBackendError: no OpenGL backend works here (MuJoCo envs).
        FileNotFoundError: no saved model for that agent and seed.
        OSError: the video cannot be written (a full disk, a read-only folder); nothing is
            left next to the run.
    """
    from ermrl.analysis._replay import load_trained_agent, rollout

    trained = load_trained_agent(run, agent, seed)
    backend = select_gl_backend(gl) if (gl or _needs_gl(trained.env_id)) else None
    episode = rollout(
        trained,
        max_steps=max_steps,
        deterministic=deterministic,
        env_seed=env_seed,
        render=True,
        fast_render=fast,
    )
    if not episode.frames:
        raise RuntimeError(f"{trained.env_id} rendered no frame")
    mp4 = (
        Path(out)
        if out is not None
        else Path(run) / "videos" / f"{trained.agent}_seed{trained.seed}.mp4"
    )
    names: list[str] = []
    # Staged, then moved next to the run: a full disk or a read-only folder (OSError) leaves
    # no partial video.
    with staged_folder(mp4.parent) as stage:
        try:
            names.append(write_mp4(episode.frames, stage / mp4.name, episode.fps).name)
        except OSError:
            raise
        except Exception as err:  # no ffmpeg: fall back to a GIF rather than nothing
            warnings.warn(f"could not write {mp4} ({err}); writing a GIF instead", stacklevel=2)
            gif = True
        if gif:
            gif_path = stage / mp4.with_suffix(".gif").name
            names.append(write_gif(episode.frames, gif_path, episode.fps).name)
    paths = [mp4.parent / name for name in names]
    height, width = episode.frames[0].shape[:2]
    return VideoResult(
        paths=tuple(paths),
        n_frames=len(episode.frames),
        fps=episode.fps,
        size=(int(height), int(width)),
        episode_return=episode.episode_return,
        backend=backend,
    )
