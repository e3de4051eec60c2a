"""``mcsm-client`` commands that drive a map with many inputs, served or in process:
``play`` (a dataset), ``play-rosbag``, ``sim`` (the paper's simulation) and ``multirobot``
(the parser and ``main``: :mod:`mcsm_client.cli`).
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
from typing import Any

import numpy as np

from mcsm_client.cli_common import (
    EXIT_OK,
    EXIT_REFUSED,
    EXIT_USAGE,
    UsageError,
    _check_output,
    _client,
    _map_for,
    _prefix,
    _print,
    _Progress,
)


def cmd_play(args: argparse.Namespace) -> int:
    """``play``: stream a dataset; exit 1 if the map refused any constraint."""
    from mcsm_client.datasets import DatasetError, read_dataset
    from mcsm_client.players import play

    try:
        ds = read_dataset(args.file, noise=args.noise)
    except (OSError, DatasetError, ValueError) as exc:
        raise UsageError(str(exc)) from None
    counts = ds.counts()
    print(f"{ds.name}: {len(ds.constraints)} constraints ({counts['odometry']} odometry, "
          f"{counts['loop_closure']} loop closures, {counts['landmark']} landmark sightings; "
          f"{counts['poses']} poses, {counts['landmarks']} landmarks; noise read as "
          f"{ds.noise})", file=sys.stderr, flush=True)
    target, closer = _map_for(args)
    try:
        stats = play(ds, target, rng=np.random.default_rng(args.seed), bounded=args.bounded,
                     order=args.order, max_constraints=args.max_constraints,
                     progress=_Progress("play", not args.no_progress),
                     stop_on_error=args.stop_on_error)
    finally:
        if closer is not None:
            closer.close()
    obj = {"file": ds.name, "total": stats.total, "applied": stats.applied,
           "results": stats.results, "skipped": stats.skipped, "rejected": stats.rejected,
           "removed": stats.removed, "elapsed_s": stats.elapsed_s,
           "first_error": stats.first_error}
    text = stats.summary() + (f"\nfirst refusal: {stats.first_error}" if stats.first_error
                              else "")
    _print(args, obj, text)
    return EXIT_REFUSED if stats.rejected else EXIT_OK


def cmd_play_rosbag(args: argparse.Namespace) -> int:
    """``play-rosbag``: a ROS 2 bag through the node's mapping; exit 1 if anything was refused
    or rejected, or a message was invalid."""
    if importlib.util.find_spec("rosbags") is None:
        raise UsageError("play-rosbag needs rosbags: pip install 'mcsm[ros]'")
    from mcsm_client.ros2.bag import BagError, play_rosbag
    from mcsm_client.ros2.mapping import MappingOptions

    d = MappingOptions()
    opts = MappingOptions(
        odometry_topics=tuple(args.odometry_topic or d.odometry_topics),
        constraint_topics=tuple(args.constraint_topic or d.constraint_topics),
        landmark_topics=tuple(args.landmark_topic or d.landmark_topics),
        frame_prefix=args.frame_prefix, keyframe_distance_m=args.keyframe_distance_m,
        keyframe_angle_rad=args.keyframe_angle_rad)
    bar = _Progress("play-rosbag", not args.no_progress)
    try:
        with _client(args) as c:
            stats = play_rosbag(args.bag, c, opts, progress=bar)
    except BagError as exc:
        raise UsageError(str(exc)) from None
    text = stats.summary() + (f"\nfirst problem: {stats.first_error}" if stats.first_error
                              else "")
    _print(args, {"bag": str(args.bag), **stats.as_dict()}, text)
    return EXIT_REFUSED if (stats.rejected or stats.n_refused or stats.invalid) else EXIT_OK


def cmd_sim(args: argparse.Namespace) -> int:
    """``sim``: the paper's §6 simulation with per-iteration scores."""
    from mcsm_client.sim import SimConfig, plot_results, run_sim

    if args.iterations < 1 or args.score_every < 1 or args.landmarks < 1:
        raise UsageError("--iterations, --score-every and --landmarks must be >= 1")
    _check_output(args.csv, "--csv", args.force)  # before the run, not after it
    _check_output(args.png, "--png", args.force)
    if args.png is not None and importlib.util.find_spec("matplotlib") is None:
        raise UsageError("--png needs matplotlib (pip install -e '.[eval]')")
    cfg = SimConfig(n_iterations=args.iterations, sigma_theta_deg=args.sigma_theta_deg,
                    n_landmarks=args.landmarks, score_every=args.score_every,
                    bounded=not args.unbounded)
    target, closer = _map_for(args)

    def show(row: Any) -> None:
        if not args.json:
            print(f"iteration {row.iteration:5d}: {row.n_landmarks:3d} landmarks, "
                  f"RMS {row.rms_m:.3f} m, NEES/dof {row.nees_per_dof:.2f}", flush=True)

    try:
        res = run_sim(cfg, target, rng=np.random.default_rng(args.seed), progress=show)
    finally:
        if closer is not None:
            closer.close()
    if args.csv is not None:
        res.write_csv(args.csv)
    if args.png is not None:
        try:
            plot_results({f"N={res.n_samples}": res}, args.png)
        except ImportError as exc:
            print(f"mcsm-client sim: {exc}", file=sys.stderr)
            return EXIT_USAGE
    _print(args, res.as_dict(), res.summary())
    return EXIT_OK


def cmd_multirobot(args: argparse.Namespace) -> int:
    """``multirobot``: the two-robot join and cross loop closure demo."""
    from mcsm_client.multirobot import MultiRobotConfig, run_multirobot

    if args.connect_b and args.map_b and args.in_process is not None:
        raise UsageError("--in-process cannot be combined with --connect-b/--map-b")
    if args.landmarks < 1:
        raise UsageError("--landmarks must be >= 1")
    rng = np.random.default_rng(args.seed)
    cfg = MultiRobotConfig(n_landmarks=args.landmarks)
    log = None if args.json else (lambda s: print(s, flush=True))
    if args.in_process is not None:
        from mcsm import StochasticMap

        from mcsm_client.players import MapTarget

        prefix = _prefix(args)
        a_map = MapTarget(StochasticMap(args.in_process), prefix)
        b_map = MapTarget(StochasticMap(args.in_process), prefix)
        res = run_multirobot(cfg, a_map, b_map, rng=rng, log=log)
    else:
        ca, closer_a = _map_for(args)
        try:
            if args.connect_b or args.map_b:
                over: dict[str, Any] = {}
                if args.connect_b:
                    over["connect"] = args.connect_b
                if args.map_b:
                    over["map"] = args.map_b
                cb, closer_b = _map_for(args, **over)
                try:
                    res = run_multirobot(cfg, ca, cb, rng=rng, log=log)
                finally:
                    closer_b.close()
            else:
                res = run_multirobot(cfg, ca, rng=rng, log=log)
        finally:
            closer_a.close()
    obj = {"scores": [vars(s) for s in res.scores], "join": res.join_kind,
           "import": res.import_kind, "cross_loop_closures": res.cross_loop_closures,
           "elapsed_s": res.elapsed_s}
    _print(args, obj, res.summary())
    return EXIT_OK


