"""`mam eval RUN_DIR`: run a trained actor for N episodes, print its returns, optionally record a video.

It reads RUN_DIR/checkpoints/policy.npz with numpy (`mam_core.policy.load_policy`): no Zenoh,
no learner, no torch. By default it reproduces the run's final evaluation: the same seed
(summary.json's `final_eval.seed`, else the referee's rule `eval_seed(seed, env_steps)`), the
same episodes (episode i is reset with seed + i) and deterministic actions, so the returns equal
the final returns in summary.json and the last row of eval.jsonl. `--video` renders the
episodes to an MP4 (episodes run one at a time then, with `render_mode="rgb_array"`; MuJoCo
tasks render offscreen with EGL, see docs/GUIDE.md, "Use your trained policy").
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import Any, Optional

import numpy as np
import typer

from mam_core.config import AlgoConfig
from mam_core.envs import EnvError, make_env
from mam_core.evaluation import eval_seed, rollout
from mam_core.family import family_for
from mam_core.policy import POLICY_FILE, EnvSpec, PolicyFileError, TrainedPolicy, load_policy, policy_path
from services.run import rundir
from services.run.config import check_env_kwargs


def _fail(message: str) -> typer.Exit:
    typer.echo(f"mam eval: {message}", err=True)
    return typer.Exit(2)


def _summary(run_dir: Path) -> dict[str, Any]:
    return rundir.read_json(run_dir / rundir.SUMMARY)


def open_policy(run_dir: Path, actor: str) -> TrainedPolicy:
    """load_policy with clear errors; a run directory from before policy.npz is converted once."""
    path = policy_path(run_dir)
    if not path.exists() and path.name == POLICY_FILE and (path.parent / rundir.LEARNER_CHECKPOINT).is_file():
        from services.roles.policy_export import export_from_checkpoint  # torch, once, for old run directories

        typer.echo(f"no {POLICY_FILE} yet: writing it from checkpoints/learner.pt", err=True)
        try:
            export_from_checkpoint(run_dir)
        except Exception as e:  # a corrupt learner.pt: torch's own error says what is wrong
            raise _fail(f"cannot read {path.parent / 'learner.pt'}: {type(e).__name__}: {e}") from None
    try:
        return load_policy(run_dir, actor=actor)
    except FileNotFoundError as e:
        raise _fail(str(e)) from None
    except (PolicyFileError, ValueError) as e:
        raise _fail(str(e)) from None


def check_env_matches(pi: TrainedPolicy, env_id: str, env_kwargs: dict[str, Any]) -> None:
    try:
        spec = EnvSpec.from_env_id(env_id, env_kwargs)
    except EnvError as e:
        raise _fail(str(e)) from None
    if (spec.obs_dim, spec.act_dim) != (pi.spec.obs_dim, pi.spec.act_dim) or \
            not np.allclose(spec.max_action, pi.spec.max_action):
        raise _fail(f"env {env_id!r} does not match the policy: it has obs_dim {spec.obs_dim}, act_dim "
                    f"{spec.act_dim}, max_action {list(spec.max_action)}; the policy was trained on "
                    f"{pi.env_id!r} with obs_dim {pi.spec.obs_dim}, act_dim {pi.spec.act_dim}, max_action "
                    f"{list(pi.spec.max_action)}")


def with_noise(pi: TrainedPolicy, sigma: float, seed: int):
    """The run's algorithm family's acting rule with noise (mam_core.family `explorer`): TD3's
    a + N(0, σ·max_action), clipped to the bounds; SAC's actions sampled from π(·|s). It draws
    from one generator seeded with `seed`."""
    try:
        family = family_for(str(pi.meta.get("algo") or AlgoConfig().algo))
    except ValueError as e:
        raise _fail(str(e)) from None
    return family.explorer(pi, sigma, np.random.default_rng(seed))


def lengths_text(lengths: Any) -> str:
    """The episode lengths in one phrase: "length 200 (every episode)", or their range and mean (each
    episode's own is on its line above)."""
    lengths = [int(n) for n in lengths]
    if len(set(lengths)) == 1:
        return f"length {lengths[0]} ({'every episode' if len(lengths) > 1 else 'one episode'})"
    return f"lengths {min(lengths)}–{max(lengths)} (mean {sum(lengths) / len(lengths):.1f})"


def record_episodes(policy: Any, env_id: str, env_kwargs: dict[str, Any], episodes: int, seed: int,
                    video: Path) -> tuple[np.ndarray, np.ndarray, int]:
    """Episodes one at a time with rgb_array frames into an MP4 (H.264); (returns, lengths, frames)."""
    import imageio.v2 as imageio

    os.environ.setdefault("MUJOCO_GL", "egl")  # offscreen GL on a headless box (before mujoco renders)
    try:
        env = make_env(env_id, env_kwargs, render_mode="rgb_array")
    except EnvError as e:
        raise _fail(str(e)) from None
    except (ValueError, TypeError) as e:
        raise _fail(f"env {env_id!r} cannot render rgb_array frames: {e}") from None
    returns, lengths, frames = np.zeros(episodes), np.zeros(episodes, np.int64), 0
    fps = int(env.metadata.get("render_fps") or 30)
    writer = None
    space = env.action_space
    try:
        for i in range(episodes):
            obs, _ = env.reset(seed=seed + i)
            done = False
            while True:
                try:
                    frame = env.render()
                except Exception as e:  # no GL context: say what to install
                    raise _fail(f"rendering {env_id!r} failed ({type(e).__name__}: {e}). MuJoCo tasks render "
                                f"offscreen with MUJOCO_GL={os.environ.get('MUJOCO_GL')}: install EGL "
                                "(Debian/Ubuntu: apt-get install libegl1 libegl-mesa0), or OSMesa "
                                "(apt-get install libosmesa6, then MUJOCO_GL=osmesa)") from None
                if frame is None or np.asarray(frame).ndim != 3:
                    raise _fail(f"env {env_id!r} returned no rgb_array frame")
                if writer is None:
                    video.parent.mkdir(parents=True, exist_ok=True)
                    writer = imageio.get_writer(str(video), fps=fps, codec="libx264", pixelformat="yuv420p",
                                                macro_block_size=2, quality=7)
                writer.append_data(np.asarray(frame, np.uint8))
                frames += 1
                if done:
                    break
                action = np.asarray(policy(np.asarray(obs, np.float32)[None]), np.float32).reshape(space.shape)
                action = np.clip(action, space.low, space.high)
                obs, reward, terminated, truncated, _ = env.step(action)
                returns[i] += float(reward)
                lengths[i] += 1
                done = terminated or truncated
    finally:
        if writer is not None:
            writer.close()
        env.close()
    return returns, lengths, frames


def eval_command(
    run_dir: Path = typer.Argument(..., help="a run directory (or a policy .npz file)"),
    actor: str = typer.Option("survivor", "--actor", help="actor index K, or 'survivor' (before an elimination: "
                              "the best actor of the last evaluation)"),
    episodes: Optional[int] = typer.Option(None, "--episodes", help="episodes (default: as many as the run's "
                                           "final evaluation)"),
    seed: Optional[int] = typer.Option(None, "--seed", help="episode i is reset with seed + i (default: the seed "
                                       "of the run's final evaluation)"),
    video: Optional[Path] = typer.Option(None, "--video", help="render the episodes to this MP4 file"),
    deterministic: bool = typer.Option(True, "--deterministic/--noise", help="deterministic actions (as the "
                                       "referee evaluates; SAC: the mean action), or with the workers' Gaussian "
                                       "exploration noise (SAC: actions sampled from the policy, seeded from --seed)"),
    env: Optional[str] = typer.Option(None, "--env", help="evaluate on another env id (must match the policy's "
                                      "observation and action spaces)"),
    env_kwargs: Optional[str] = typer.Option(None, "--env-kwargs", help="JSON kwargs for gym.make (default: "
                                             "the run's)"),
    as_json: bool = typer.Option(False, "--json", help="print one JSON object instead of the table"),
) -> None:
    """Run a trained actor (numpy only): mean ± std return, episode lengths, and optionally an MP4."""
    if not run_dir.exists():
        raise _fail(f"{run_dir} does not exist")
    pi = open_policy(run_dir, actor)
    meta = pi.meta
    root = run_dir if run_dir.is_dir() else None
    summary = _summary(root) if root is not None else {}
    final = summary.get("final_eval") if isinstance(summary.get("final_eval"), dict) else {}
    env_id = env or pi.env_id
    try:
        kwargs = check_env_kwargs(env_kwargs) if env_kwargs is not None else dict(pi.env_kwargs)
    except ValueError as e:
        raise _fail(f"--env-kwargs: {e}") from None
    check_env_matches(pi, env_id, kwargs)
    if seed is None:
        seed = int(final["seed"]) if "seed" in final else eval_seed(int(meta.get("seed", 0)),
                                                                    int(meta.get("env_steps", 0)))
    if episodes is None:
        episodes = int(final.get("episodes") or meta.get("eval_episodes") or 10)
    if episodes < 1:
        raise _fail("--episodes must be >= 1")
    policy = pi if deterministic else with_noise(pi, float(meta.get("explore_noise", 0.1)), seed)
    frames = 0
    if video is not None:
        returns, lengths, frames = record_episodes(policy, env_id, kwargs, episodes, seed, video)
    else:
        try:
            r = rollout(policy, env_id, episodes, seed, env_kwargs=kwargs)
        except EnvError as e:
            raise _fail(str(e)) from None
        returns, lengths = r.returns, r.lengths
    versions = meta.get("versions")
    same_weights = bool(final.get("versions")) and versions is not None and \
        final["versions"][pi.actor] == versions[pi.actor]
    result = {"run": meta.get("run"), "env_id": env_id, "env_kwargs": kwargs, "actor": pi.actor,
              "env_steps": meta.get("env_steps"), "version": None if versions is None else versions[pi.actor],
              "deterministic": deterministic, "seed": seed, "episodes": episodes,
              "returns": [float(x) for x in returns], "lengths": [int(x) for x in lengths],
              "mean": float(np.mean(returns)), "std": float(np.std(returns)),
              "final_eval_weights": same_weights}
    if video is not None:
        result.update(video=str(video), frames=frames)
    if as_json:
        typer.echo(json.dumps(result))
        return
    survivor = " (survivor)" if meta.get("survivor") == pi.actor else ""
    typer.echo(f"run {meta.get('run')}  env {env_id}  actor {pi.actor}{survivor}  weights at "
               f"{meta.get('env_steps')} transitions (version {result['version']})  "
               f"{'deterministic' if deterministic else 'sampled' if pi.stochastic else 'with exploration noise'}  "
               f"seed {seed}")
    for i, (ret, n) in enumerate(zip(returns, lengths)):
        typer.echo(f"  episode {i:3d}  return {ret:12.3f}  length {n:5d}")
    typer.echo(f"return {result['mean']:.3f} ± {result['std']:.3f} (std) over {episodes} episode(s); "
               f"{lengths_text(lengths)}")
    if video is not None:
        typer.echo(f"video {video} ({frames} frames)")
    sys.stdout.flush()
