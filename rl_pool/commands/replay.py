"""``rl-pool replay``: render an agent offscreen to a GIF (Pillow) or MP4 (ffmpeg).

MuJoCo renders headless through EGL (``MUJOCO_GL=egl``, set here before MuJoCo is
imported unless the user chose another backend; no other command picks one).
"""

from __future__ import annotations

import os
import shutil
import subprocess

from rl_pool.errors import UsageError


def replay_path(target: str, out: str, steps: int = 0, seed: int = 0, fps: int = 30,
                width: int = 480, height: int = 360, camera: str | None = None) -> str:
    """Render one episode of the agent; ``camera``: a camera of the model (default: one
    named "track" if the model has it, so a swimmer that travels stays in view)."""
    from rl_pool.commands.evaluate import resolve_agent

    ext = os.path.splitext(out)[1].lower()
    if ext not in (".gif", ".mp4"):
        raise UsageError(f"--out must end in .gif or .mp4, got {out!r}")
    if ext == ".mp4" and shutil.which("ffmpeg") is None:
        raise UsageError("writing .mp4 needs ffmpeg on PATH; use a .gif instead")
    if width < 16 or height < 16 or fps < 1 or steps < 0:
        raise UsageError("--width/--height must be >= 16, --fps >= 1, --steps >= 0")
    os.environ.setdefault("MUJOCO_GL", "egl")
    path, data = resolve_agent(target)
    from rl_pool.learning import envs
    from rl_pool.maths.agent import Agent

    agent = Agent.from_bytes(data, source=path)
    kwargs = dict(agent.meta.env_kwargs, max_episode_steps=agent.meta.max_episode_steps,
                  width=width, height=height)
    try:
        env, _ = envs.make(agent.meta.env, kwargs, render_mode="rgb_array")
        names = [env.model.camera(k).name for k in range(env.model.ncam)] if hasattr(env, "model") else []
        if camera is not None and camera not in names:
            raise UsageError(f"--camera {camera!r}: the model's cameras are {names}")
        camera = camera or ("track" if "track" in names else None)
        if camera is not None:
            env.close()
            env, _ = envs.make(agent.meta.env, kwargs | {"camera_name": camera}, render_mode="rgb_array")
    except UsageError:
        raise
    except Exception as exc:
        raise UsageError(f"cannot render {agent.meta.env} offscreen ({exc}); try MUJOCO_GL=osmesa") from None
    steps = steps or agent.meta.max_episode_steps
    # The env runs at 1/dt steps per second; render every k-th step to play in real time at ``fps``.
    stride = max(1, round((1.0 / env.dt) / fps))
    real_fps = (1.0 / env.dt) / stride
    obs, _ = env.reset(seed=seed)
    frames = [env.render()]
    total, n = 0.0, 0
    for _ in range(steps):
        obs, reward, terminated, _, _ = env.step(agent.act(obs))
        total += reward
        n += 1
        if n % stride == 0:
            frames.append(env.render())
        if terminated:
            break
    env.close()
    if ext == ".gif":
        from PIL import Image

        images = [Image.fromarray(f) for f in frames]
        images[0].save(out, save_all=True, append_images=images[1:], duration=round(1000 / real_fps), loop=0,
                       optimize=True)
    else:
        proc = subprocess.Popen(["ffmpeg", "-y", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24",
                                 "-s", f"{width}x{height}", "-r", f"{real_fps:.3f}", "-i", "-",
                                 "-pix_fmt", "yuv420p", "-vcodec", "libx264", out], stdin=subprocess.PIPE)
        for f in frames:
            proc.stdin.write(f.tobytes())
        proc.stdin.close()
        if proc.wait() != 0:
            raise UsageError("ffmpeg failed to write the video")
    print(f"{len(frames)} frames at {real_fps:.1f} fps; return {total:.2f} over {n} steps")
    return out
