"""``make run``: a server, the paper's simulation and the multi-robot demo, end to end.

What it does, all on loopback (no network, no second machine):

1. starts ``mcsm serve`` as a subprocess on a free port of 127.0.0.1, recording to
   ``recordings/run-<UTC time>/server.mcap``, and waits for its ``listening on`` line;
2. runs the paper's §6 simulation client (PAPER §4) against it for one revolution (340
   iterations: the big loop closes), scoring landmark RMS error and NEES per dof against ground
   truth; writes ``sim.csv`` and ``sim.png``;
3. starts a second server for robot B and runs the multi-robot demo (two maps, rendezvous
   join through ``export_submap``/``import_submap``, loop closures across robots);
4. stops the servers with SIGINT (their recordings are closed cleanly; ``mcsm replay`` checks
   them), replays the simulation's recording once and writes a picture of its final map,
   ``map.png`` (``mcsm plot``, with the ground truth from ``truth.csv``), and ``scene.mcap``,
   the map over time for the Foxglove app (``mcsm export foxglove``; needs the ``viz`` extra);
5. prints an accuracy summary and where the files are.

Run ``python -m mcsm_client.demo --help`` for the knobs (N, iterations, seed, output folder).
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mcsm_client.process import ServerProcess, free_port

__all__ = ["DemoConfig", "ServerProcess", "draw_map", "free_port", "main", "run_demo"]


@dataclass(frozen=True)
class DemoConfig:
    """Knobs of ``make run`` (defaults: one revolution at N = 1000, about a minute here)."""

    n_samples: int = 1000
    n_iterations: int = 340
    score_every: int = 10
    sigma_theta_deg: float = 0.0
    seed: int = 2012
    out_dir: Path | None = None
    multirobot: bool = True
    multirobot_samples: int = 500
    scene_every: int = 50


@dataclass
class DemoReport:
    """Files written and figures measured."""

    out_dir: Path
    files: list[Path] = field(default_factory=list)
    figures: dict[str, Any] = field(default_factory=dict)


def run_demo(config: DemoConfig, *, log: Any = print) -> DemoReport:
    """Run the whole demo (see the module docstring). Returns what it wrote and measured."""
    from mcsm_client.client import MapClient
    from mcsm_client.multirobot import MultiRobotConfig, run_multirobot
    from mcsm_client.sim import SimConfig, plot_results, run_sim

    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    out = config.out_dir or Path("recordings") / f"run-{stamp}"
    out.mkdir(parents=True, exist_ok=True)
    report = DemoReport(out_dir=out)
    rng = np.random.default_rng(config.seed)
    sim_rng, mr_rng = rng.spawn(2)
    # the scenario run_sim will draw (from its first child of sim_rng), for the ground truth
    scenario = _sim_scenario(copy.deepcopy(sim_rng), config)

    log(f"[1/4] starting mcsm serve (N={config.n_samples}) ...")
    with ServerProcess(out / "server.mcap", n_samples=config.n_samples) as server:
        log(f"      listening on {server.endpoint}, recording {server.record}")
        with MapClient(connect=server.endpoint, timeout_s=30.0) as client:
            client.wait_for_server(timeout_s=30.0)
            log(f"[2/4] paper §6 simulation: {config.n_iterations} iterations, "
                f"sigma_theta={config.sigma_theta_deg} deg")

            def show(row: Any) -> None:
                if row.iteration % 50 == 0 or row.iteration == config.n_iterations:
                    log(f"      iteration {row.iteration:4d}: {row.n_landmarks:3d} landmarks, "
                        f"RMS {row.rms_m:.3f} m, NEES/dof {row.nees_per_dof:.2f} "
                        f"({row.elapsed_s:.0f} s)")

            sim_cfg = SimConfig(n_iterations=config.n_iterations,
                                sigma_theta_deg=config.sigma_theta_deg,
                                score_every=config.score_every)
            sim = run_sim(sim_cfg, client, rng=sim_rng, scenario=scenario, progress=show)
            info = client.info()
        report.files.append(sim.write_csv(out / "sim.csv"))
        try:
            report.files.append(plot_results({f"N={sim.n_samples}": sim}, out / "sim.png",
                                             title="paper §6 scenario over mcsm serve"))
        except ImportError as exc:
            log(f"      (no plot: {exc})")
        report.figures["sim"] = sim.as_dict()
        report.figures["server"] = {"seq": info.seq, "digest": info.digest,
                                    "frames": info.n_frames}
        log(f"      {sim.summary()}")

        if config.multirobot:
            log(f"[3/4] multi-robot demo: robot B on its own server (N="
                f"{config.multirobot_samples})")
            mr_maps = ServerProcess(out / "robot-a.mcap", n_samples=config.multirobot_samples)
            mr_b = ServerProcess(out / "robot-b.mcap", n_samples=config.multirobot_samples)
            with mr_maps as srv_a, mr_b as srv_b, \
                    MapClient(connect=srv_a.endpoint, timeout_s=30.0) as ca, \
                    MapClient(connect=srv_b.endpoint, timeout_s=30.0) as cb:
                ca.wait_for_server(timeout_s=30.0)
                cb.wait_for_server(timeout_s=30.0)
                mr = run_multirobot(MultiRobotConfig(), ca, cb, rng=mr_rng,
                                    log=lambda s: log(f"      {s}"))
            for line in mr.summary().splitlines():
                log(f"      {line}")
            report.figures["multirobot"] = {
                "scores": [vars(s) for s in mr.scores], "join": mr.join_kind,
                "cross_loop_closures": mr.cross_loop_closures}
            report.files += [srv_a.record, srv_b.record]
    report.files.insert(0, server.record)
    log("[4/4] pictures of the simulation's map: replaying its recording")
    report.files += draw_map(server.record, out, truth=_truth_rows(scenario, sim.final.iteration),
                             every=config.scene_every, log=lambda s: log(f"      {s}"))
    report.files.append(out / "summary.json")
    log("")
    log("accuracy summary")
    f = sim.final
    log(f"  paper §6 sim, N={sim.n_samples}, after {f.iteration} iterations: landmark RMS "
        f"{f.rms_m:.3f} m, NEES/dof {f.nees_per_dof:.2f} ({f.n_landmarks} landmarks)")
    if config.multirobot:
        for s in mr.scores[-2:]:
            log(f"  multi-robot {s.stage}: RMS {s.rms_m:.3f} m, NEES/dof {s.nees_per_dof:.2f}")
    codes = [server.returncode] + ([srv_a.returncode, srv_b.returncode]
                                   if config.multirobot else [])
    report.figures["server_exit_codes"] = codes
    log(f"servers stopped with SIGINT (exit codes {codes}); files in {out}/:")
    for p in report.files:
        log(f"  {p}")
    log(f"check a recording replays bit-identically: .venv/bin/mcsm replay {server.record}")
    if (out / "scene.mcap").exists():
        log(f"see the map: open {out / 'map.png'}, or drag {out / 'scene.mcap'} into the "
            "Foxglove app (3D panel, display frame mcsm@default); a live map: .venv/bin/mcsm "
            "view --connect <endpoint> (docs/visualising.md)")
    (out / "summary.json").write_text(json.dumps(report.figures, indent=2, default=str))
    return report


def _sim_scenario(sim_rng: np.random.Generator, config: DemoConfig) -> Any:
    """The scenario ``run_sim`` generates from ``sim_rng`` (same children, same draws)."""
    from mcsm_client.scenario import generate_paper_scenario
    from mcsm_client.sim import SimConfig

    scen_rng, _ = sim_rng.spawn(2)
    cfg = SimConfig(n_iterations=config.n_iterations, sigma_theta_deg=config.sigma_theta_deg,
                    score_every=config.score_every)
    return generate_paper_scenario(cfg.scenario_config(), scen_rng)


def _truth_rows(scenario: Any, k: int) -> list[tuple[str, float, float]]:
    """Ground truth in x0's frame: every landmark and the robot's last pose ``x{k}``."""
    from mcsm_client.scenario import landmark_frame, landmarks_in_frame, pose_frame

    rows = [(landmark_frame(j), float(p[0]), float(p[1]))
            for j, p in enumerate(landmarks_in_frame(scenario, 0))]
    return rows + [(pose_frame(k), float(scenario.poses[k][0]), float(scenario.poses[k][1]))]


def draw_map(record: Path, out: Path, *, truth: list[tuple[str, float, float]] | None = None,
             every: int = 50, log: Any = print) -> list[Path]:
    """``scene.mcap`` (``mcsm export foxglove``) and ``map.png`` (``mcsm plot``) of the map
    ``default`` of ``record``, from one replay; ``truth.csv`` beside them when ``truth`` is
    given. Without the ``viz`` extra it says so and returns no files."""
    from mcsm.errors import McsmError
    from mcsm.viz.foxglove_scene import export_foxglove
    from mcsm.viz.plot import plot_map
    from mcsm.viz.scene import read_truth

    files = []
    truth_xyz = None
    if truth:
        path = out / "truth.csv"
        path.write_text("frame,x,y\n" + "".join(f"{f},{x!r},{y!r}\n" for f, x, y in truth))
        files.append(path)
        truth_xyz = read_truth(path)
    try:
        rep = export_foxglove(record, out / "scene.mcap", every=every, map_name="default",
                              overwrite=True)
    except McsmError as exc:
        log(f"(no map pictures: {exc})")
        return files
    files.append(rep.path)
    log(f"{rep.path}: {len(rep.snapshots)} snapshots up to seq {rep.final_seq} for Foxglove")
    for note in rep.notes:
        log(f"warning: {note}")
    if rep.final_view is not None:
        try:
            res = plot_map(rep.final_view, out / "map.png", truth=truth_xyz)
        except McsmError as exc:
            log(f"(no map.png: {exc})")
            return files
        files.append(res.path)
        log(f"{res.path}: the map at seq {rep.final_view.seq} ({len(rep.final_view.frames)} "
            f"frames, view {res.view})")
    return files


def main(argv: list[str] | None = None) -> int:
    """``python -m mcsm_client.demo`` (what ``make run`` executes)."""
    p = argparse.ArgumentParser(prog="python -m mcsm_client.demo",
                                description="Start a server, run the paper simulation and the "
                                            "multi-robot demo against it, print the accuracy.")
    p.add_argument("--samples", type=int, default=DemoConfig.n_samples, metavar="N",
                   help=f"samples per AT (default {DemoConfig.n_samples})")
    p.add_argument("--iterations", type=int, default=DemoConfig.n_iterations,
                   help=f"simulation iterations (default {DemoConfig.n_iterations}, one lap)")
    p.add_argument("--sigma-theta-deg", type=float, default=0.0,
                   help="odometry heading noise in degrees (default 0, PAPER Fig. 4)")
    p.add_argument("--seed", type=int, default=DemoConfig.seed)
    p.add_argument("--out", type=Path, default=None,
                   help="output folder (default recordings/run-<UTC time>/)")
    p.add_argument("--robot-samples", type=int, default=DemoConfig.multirobot_samples,
                   metavar="N", help="samples per AT of the multi-robot maps (default "
                                     f"{DemoConfig.multirobot_samples})")
    p.add_argument("--no-multirobot", action="store_true", help="skip the multi-robot part")
    args = p.parse_args(argv)
    if args.samples < 2 or args.robot_samples < 2 or args.iterations < 1:
        p.error("--samples and --robot-samples must be >= 2, --iterations >= 1")
    cfg = DemoConfig(n_samples=args.samples, n_iterations=args.iterations,
                     sigma_theta_deg=args.sigma_theta_deg, seed=args.seed, out_dir=args.out,
                     multirobot=not args.no_multirobot, multirobot_samples=args.robot_samples)
    try:
        run_demo(cfg)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except RuntimeError as exc:
        print(f"demo failed: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
