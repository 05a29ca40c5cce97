"""python -m saver_actor (or saver-actor): act for a learner, provide PCPN samples,
print the learner's [env] section, or time the actor against the bare env.

  saver-actor act      --factory saver_actor.examples:reacher --learner http://127.0.0.1:50051 --envs 4
  saver-actor act      --env-id Pendulum-v1 --aligned 0:2 --max-change 0.2 ...
  saver-actor samples  --factory ... --pcpn http://127.0.0.1:50052
  saver-actor describe --factory ...
  saver-actor check    --factory ... [--steps 500]      (before a long run: the declaration holds)
  saver-actor enjoy    --factory ... --weights best.safetensors [--video out.mp4]
  saver-actor evaluate --factory ... --learner URL --out best.safetensors [--every 60]
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading

from .actor import Actor, Connection, LinkLost, Refused
from .env import EnvDecl, EnvError, factory_function
from .samples import provide_samples


def _floats(s):
    return [float(v) for v in s.split(",")] if s else None


def env_of(args):
    """(make_env, decl) from --factory module:function or from --env-id and the flags."""
    if args.factory:
        # The user's module sits where they run the command (the console script's
        # sys.path starts at its own bin folder, not there).
        if os.getcwd() not in sys.path:
            sys.path.insert(0, os.getcwd())
        try:
            factory = factory_function(args.factory)
        except ValueError as e:
            sys.exit(str(e))
        return factory()
    if not args.env_id or not args.aligned or args.max_change is None:
        sys.exit("give --factory module:function, or --env-id with --aligned and --max-change")
    import gymnasium as gym

    kwargs = json.loads(args.env_kwargs) if args.env_kwargs else {}

    def make_env():
        return gym.make(args.env_id, **kwargs)

    probe = make_env()
    decl = EnvDecl.for_env(probe, name=args.name or args.env_id.replace("/", "-").lower(), aligned=args.aligned,
                           max_change=args.max_change, obs_low=_floats(args.obs_low), obs_high=_floats(args.obs_high),
                           goal=args.goal, success_radius=args.success_radius)
    probe.close()
    return make_env, decl


def connection(url, args):
    token = open(args.token_file).read().strip() if args.token_file else None
    ca = open(args.ca, "rb").read() if args.ca else None
    return Connection(url=url, token=token, ca=ca)


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def main(argv=None):
    # SIGTERM (docker stop, kill) stops as Ctrl-C does: the envs closed, one line said.
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _interrupt)
    ap = argparse.ArgumentParser(prog="saver-actor", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    cmds = {c: sub.add_parser(c, formatter_class=argparse.ArgumentDefaultsHelpFormatter)
            for c in ("act", "samples", "describe", "check", "enjoy", "evaluate")}
    for p in cmds.values():
        p.add_argument("--factory", help="module:function returning (make_env, EnvDecl)")
        p.add_argument("--env-id", help="a Gymnasium env id (with --aligned and --max-change)")
        p.add_argument("--env-kwargs", help="JSON keyword arguments of gym.make")
        p.add_argument("--name", help="the env's name in the run (default: from the id)")
        p.add_argument("--aligned", help="observation entries of the state-aligned position, START:STOP")
        p.add_argument("--goal", help="observation entries of the goal, START:STOP (default: goal 0)")
        p.add_argument("--max-change", type=float, help="largest one-step change of an aligned entry")
        p.add_argument("--obs-low", help="comma-separated lower bound of every observation entry")
        p.add_argument("--obs-high", help="comma-separated upper bound of every observation entry")
        p.add_argument("--success-radius", type=float, help="success when every |p - g| is below it")
        p.add_argument("--token-file", help="the learner's (and store's) token")
        p.add_argument("--ca", help="CA certificate (PEM) of https:// servers")
    a = cmds["act"]
    a.add_argument("--learner", default="http://127.0.0.1:50051", help="the learner's URL")
    a.add_argument("--envs", type=int, default=1, help="env instances stepped per rollout")
    a.add_argument("--env-processes", type=int, default=0, metavar="N",
                   help="step the envs in N worker processes at once (0: in this process, one after another)")
    a.add_argument("--actor-name", help="name in the learner's logs")
    a.add_argument("--pcpn-samples", metavar="URL", help="also answer this pcpn-trainer's demands for samples")
    a.add_argument("--connect-timeout", type=float, default=600.0, metavar="SECONDS",
                   help="give up after this long without reaching the learner (never while it says it waits for "
                        "its PCPN, nor while this actor feeds the PCPN store)")
    a.add_argument("--seed", type=int, default=0, help="seed of the PCPN samples")
    cmds["samples"].add_argument("--pcpn", required=True, metavar="URL", help="the pcpn-trainer")
    cmds["samples"].add_argument("--seed", type=int, default=0, help="seed of the walks")
    cmds["samples"].add_argument("--envs", type=int, default=16, help="env instances walked at once")
    cmds["samples"].add_argument("--connect-timeout", type=float, default=600.0, metavar="SECONDS",
                                 help="give up after this long without reaching the store")
    cmds["check"].add_argument("--steps", type=int, default=500, help="random steps to take")
    cmds["check"].add_argument("--seed", type=int, default=0)
    j = cmds["enjoy"]
    j.add_argument("--weights", required=True, help="a policy file (a run's policy.safetensors or best.safetensors, "
                                                   "saver weights --out)")
    j.add_argument("--episodes", type=int, default=5)
    j.add_argument("--video", help="write the episodes' frames here (.mp4, .gif; needs saver-actor[video])")
    j.add_argument("--stochastic", action="store_true", help="sample actions instead of the policy's mean")
    j.add_argument("--max-steps", type=int, default=1000, help="end an episode after this many steps")
    j.add_argument("--seed", type=int, default=0, help="env seed of the first episode (then +1 each)")
    v = cmds["evaluate"]
    v.add_argument("--learner", default="http://127.0.0.1:50051", help="the learner's URL")
    v.add_argument("--out", default="best.safetensors", help="the best weights so far (eval.csv beside it)")
    v.add_argument("--every", type=float, default=60.0, help="seconds between evaluations")
    v.add_argument("--episodes", type=int, default=10, help="deterministic episodes per evaluation")
    v.add_argument("--max-steps", type=int, default=1000, help="end an episode after this many steps")
    v.add_argument("--seed", type=int, default=0, help="env seed of the first episode (then +1 each)")
    args = ap.parse_args(argv)
    try:
        make_env, decl = env_of(args)
        if args.cmd == "describe":
            print(decl.toml(), end="")
            return 0
        if args.cmd == "check":
            from .check import check_env

            print(check_env(make_env, decl, steps=args.steps, seed=args.seed).text(decl))
            return 0
        if args.cmd == "enjoy":
            from .enjoy import enjoy
            from .policy import Policy

            try:
                policy = Policy.load(args.weights)
            except (OSError, ValueError) as e:
                raise EnvError(f"--weights {args.weights}: {e}") from None
            r = enjoy(make_env, decl, policy, episodes=args.episodes, deterministic=not args.stochastic,
                      seed=args.seed, max_steps=args.max_steps, video=args.video)
            for k, ep in enumerate(r.episodes):
                print(f"episode {k}: return {ep.ret:.3f}, {ep.length} steps{', success' if ep.success else ''}")
            print(f"{len(r.episodes)} episodes: mean return {r.mean_return:.3f}, success rate {r.success_rate:.2f}"
                  + (f"; {r.frames} frames in {args.video}" if args.video else ""))
            return 0
        if args.cmd == "samples":
            n = provide_samples(make_env, decl, connection(args.pcpn, args), seed=args.seed, n_envs=args.envs,
                                log=lambda m: print(m, file=sys.stderr), give_up=args.connect_timeout)
            print(f"sample provider: the store closed the call after {n} samples", file=sys.stderr)
            return 0
        if args.cmd == "evaluate":
            from .evaluate import keep_best

            best = keep_best(make_env, decl, connection(args.learner, args), args.out, every=args.every,
                             episodes=args.episodes, max_steps=args.max_steps, seed=args.seed,
                             log=lambda m: print(m, file=sys.stderr))
            print(f"the run finished; best mean return {best} in {args.out}", file=sys.stderr)
            return 0
        # The env workers (if any) start first: a process with gRPC threads should not fork.
        actor = Actor(make_env, decl, connection(args.learner, args), n_envs=args.envs, name=args.actor_name,
                      give_up=args.connect_timeout, log=lambda m: print(m, file=sys.stderr),
                      env_processes=args.env_processes)
        failed: list = []
        if args.pcpn_samples:
            conn = connection(args.pcpn_samples, args)

            def feed():
                try:
                    provide_samples(make_env, decl, conn, seed=args.seed, n_envs=args.envs, stop=actor.stop,
                                    log=lambda m: print(m, file=sys.stderr), name=actor.name)
                except Exception as e:  # the actor ends with it, saying why
                    failed.append(e)
                    actor.stop.set()
                finally:
                    actor.feeding.clear()

            actor.feeding.set()
            threading.Thread(target=feed, daemon=True).start()
        try:
            s = actor.run()
        finally:
            actor.close()
        if failed:
            raise failed[0]
        print(f"{actor.name}: run finished; {s.rollouts} rollouts, {s.steps} env steps, {s.episodes} episodes "
              f"({s.successes} successes) in {s.seconds:.1f} s", file=sys.stderr)
        return 0
    except (EnvError, Refused, LinkLost, RuntimeError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("saver-actor: stopped (Ctrl-C or SIGTERM)", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
