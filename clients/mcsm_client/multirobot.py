"""Two simulated robots build separate maps, meet, join their maps, then close a loop across.

Scenario (PAPER §3: case I joins two components, case II closes a loop), on the world of the
§6 circle (:mod:`mcsm_client.scenario`, one revolution = 340 steps):

1. Robot A drives steps ``0 .. a_steps`` (half the circle) and maps frames ``A.x*``/``A.l*``.
   Robot B drives steps ``b_start .. b_start + b_steps`` (the other half, ending near A's start)
   and maps ``B.x*``/``B.l*`` — in its own map (another server) or as its own component of
   A's map. The two maps share no frame: nothing relates them yet.
2. Rendezvous: when A stopped at ``A.x{a_steps}`` it saw B leaving ``B.x{b_start}`` a few
   metres ahead, and measured B's pose relative to its own (a planar AT with
   ``rendezvous_sigma_*``). With two servers, B's component is exported from B's server
   (``export_submap``) and imported into A's (``import_submap``), sample order intact; then this
   observation joins the two components (case I: compounding and inversion only).
3. B drives on for ``after_join_steps`` steps past A's start, now in the joined map; its sightings
   of landmarks A mapped are applied to A's landmark frames: loop closures across the two
   robots' maps (case II).

At each stage the landmark estimates are scored against ground truth (RMS error and NEES per
degree of freedom, in A's start frame ``A.x0``, the world frame). Consistency means NEES per dof
near 1; B's landmarks are only as good as the rendezvous after the join, and improve after the
cross loop closures.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mcsm_client.players import MapTarget
from mcsm_client.sampling import sample_planar
from mcsm_client.scenario import (
    PaperScenarioConfig,
    Scenario,
    generate_paper_scenario,
    landmark_nees,
    landmark_rms,
    odometry_samples,
    point_samples,
    se2_relative,
    world_to_robot,
)

__all__ = ["MultiRobotConfig", "MultiRobotResult", "Score", "run_multirobot"]


@dataclass(frozen=True)
class MultiRobotConfig:
    """Parameters of the two-robot run (steps of the 340-step circle).

    Parameters
    ----------
    a_steps : int
        Robot A drives steps ``0 .. a_steps``.
    b_start : int
        Robot B starts at pose ``b_start`` (a little ahead of A's last pose).
    b_steps : int
        Robot B's steps before the join.
    after_join_steps : int
        Robot B's steps after the join (into A's mapped area: cross loop closures).
    rendezvous_sigma_m, rendezvous_sigma_deg : float
        Noise of A's measurement of B's pose (x, y and heading).
    n_landmarks : int
        Landmarks in the world.
    bounded : bool
        Each robot keeps only its anchor (first) pose and its current pose.
    """

    a_steps: int = 170
    b_start: int = 175
    b_steps: int = 165
    after_join_steps: int = 30
    rendezvous_sigma_m: float = 0.05
    rendezvous_sigma_deg: float = 0.5
    n_landmarks: int = 200
    bounded: bool = True

    def scenario_config(self) -> PaperScenarioConfig:
        """The world: the paper's circle, long enough for both robots."""
        return PaperScenarioConfig(
            n_iterations=self.b_start + self.b_steps + self.after_join_steps,
            n_landmarks=self.n_landmarks)


@dataclass(frozen=True)
class Score:
    """Landmark estimates against ground truth at one stage."""

    stage: str
    frame: str
    n_landmarks: int
    rms_m: float
    nees_per_dof: float

    def line(self) -> str:
        """One line for people."""
        return (f"{self.stage:<28} {self.n_landmarks:4d} landmarks in {self.frame:<8} "
                f"RMS {self.rms_m:6.3f} m  NEES/dof {self.nees_per_dof:6.2f}")


@dataclass
class MultiRobotResult:
    """What happened: result kinds of the key updates, scores per stage, timings."""

    join_kind: str = ""
    import_kind: str = ""
    cross_loop_closures: int = 0
    scores: list[Score] = field(default_factory=list)
    frames_a: int = 0
    elapsed_s: float = 0.0

    def score(self, stage: str) -> Score:
        """The score of one stage (``KeyError`` if absent)."""
        for s in self.scores:
            if s.stage == stage:
                return s
        raise KeyError(stage)

    def summary(self) -> str:
        """Several lines for people."""
        lines = [s.line() for s in self.scores]
        lines.append(f"import: {self.import_kind or '(one map)'}; rendezvous update: "
                     f"{self.join_kind}; loop closures across robots: "
                     f"{self.cross_loop_closures}; {self.elapsed_s:.1f} s")
        return "\n".join(lines)


class _Robot:
    """Drives a range of scenario steps into a map under a frame-name prefix."""

    def __init__(self, name: str, scenario: Scenario, target: MapTarget, n_samples: int,
                 bounded: bool, start: int) -> None:
        self.name = name
        self.sc = scenario
        self.target = target
        self.n = n_samples
        self.bounded = bounded
        self.anchor = start
        self.current = start

    def pose(self, k: int) -> str:
        return f"{self.name}.x{k}"

    def drive(self, k_end: int, rng: np.random.Generator,
              landmark_name: Any = None) -> dict[str, int]:
        """Steps ``current .. k_end``; returns the result kinds of the sightings."""
        cfg = self.sc.config
        kinds: dict[str, int] = {}
        for k in range(self.current, k_end):
            self.target.update(self.pose(k), self.pose(k + 1),
                               odometry_samples(self.sc.odometry[k], cfg.odometry_cov, self.n,
                                                rng))
            for j, xy in self.sc.observations[k]:
                lm = landmark_name(j) if landmark_name else f"{self.name}.l{j}"
                kind = self.target.update(self.pose(k + 1), lm,
                                          point_samples(xy, cfg.laser_cov, self.n, rng))
                key = f"{kind}:{lm.split('.')[0]}"
                kinds[key] = kinds.get(key, 0) + 1
            if self.bounded and k != self.anchor:
                self.target.remove(self.pose(k))
            self.current = k + 1
        return kinds


def _score(stage: str, target: MapTarget, scenario: Scenario, anchor: str, anchor_pose: int,
           prefixes: tuple[str, ...]) -> Score:
    truth_all = world_to_robot(scenario.poses[anchor_pose], scenario.landmarks)
    frames = set(target.frames())
    means, covs, truth = [], [], []
    for prefix in prefixes:
        for j in range(truth_all.shape[0]):
            name = f"{prefix}.l{j}"
            if name in frames:
                mean, cov = target.marginal(anchor, name)
                means.append(mean[:2])
                covs.append(cov[:2, :2])
                truth.append(truth_all[j])
    if not means:
        return Score(stage, anchor, 0, float("nan"), float("nan"))
    m, c, t = np.stack(means), np.stack(covs), np.stack(truth)
    return Score(stage, anchor, len(means), landmark_rms(m, t), landmark_nees(m, c, t))


def run_multirobot(
    config: MultiRobotConfig,
    target_a: Any,
    target_b: Any | None = None,
    *,
    rng: np.random.Generator,
    log: Any = None,
) -> MultiRobotResult:
    """Run the two-robot scenario.

    Parameters
    ----------
    config : MultiRobotConfig
        Step ranges and rendezvous noise.
    target_a : StochasticMap, MapClient or MapTarget
        Robot A's map (it ends up holding the joined map). Must not hold ``A.*``/``B.*``
        frames yet.
    target_b : same kinds, optional
        Robot B's own map (e.g. a second server). ``None``: B builds its own component inside
        ``target_a`` and no export/import is needed.
    rng : np.random.Generator
        Source of all randomness (scenario, sample sets, rendezvous reading).
    log : callable, optional
        ``log(str)`` for progress lines (e.g. ``print``).

    Returns
    -------
    MultiRobotResult

    Raises
    ------
    ValueError
        If the step ranges are inconsistent.
    McsmError
        From the maps (e.g. ``FrameExists`` when ``target_a`` already holds B's frames).
    """
    c = config
    if not (0 < c.a_steps < c.b_start and c.b_steps > 0 and c.after_join_steps >= 0):
        raise ValueError("need 0 < a_steps < b_start, b_steps > 0, after_join_steps >= 0")
    say = log or (lambda _msg: None)
    t0 = time.perf_counter()
    scen_rng, a_rng, b_rng, meet_rng = rng.spawn(4)
    scenario = generate_paper_scenario(c.scenario_config(), scen_rng)
    map_a = MapTarget(target_a)
    map_b = MapTarget(target_b) if target_b is not None else map_a
    n = map_a.n_samples
    if map_b is not map_a and map_b.n_samples != n:
        raise ValueError(f"the two maps use different N ({n} and {map_b.n_samples})")
    res = MultiRobotResult()

    robot_a = _Robot("A", scenario, map_a, n, c.bounded, 0)
    robot_b = _Robot("B", scenario, map_b, n, c.bounded, c.b_start)
    say(f"robot A: steps 0..{c.a_steps}")
    robot_a.drive(c.a_steps, a_rng)
    say(f"robot B: steps {c.b_start}..{c.b_start + c.b_steps}"
        f"{' (own map)' if map_b is not map_a else ' (own component)'}")
    robot_b.drive(c.b_start + c.b_steps, b_rng)
    res.scores.append(_score("A alone", map_a, scenario, "A.x0", 0, ("A",)))
    res.scores.append(_score("B alone", map_b, scenario, f"B.x{c.b_start}", c.b_start, ("B",)))

    if map_b is not map_a:
        submap = map_b.export_component(f"B.x{c.b_start}")
        res.import_kind = map_a.import_component(submap)
        say(f"imported B's component ({len(submap.frames)} frames) into A's map")
    # A, at its last pose, measures B's pose at B's start (the rendezvous).
    truth = se2_relative(scenario.poses[c.a_steps], scenario.poses[c.b_start])
    sig = np.array([c.rendezvous_sigma_m, c.rendezvous_sigma_m,
                    np.deg2rad(c.rendezvous_sigma_deg)])
    reading = truth + sig * meet_rng.standard_normal(3)
    x_meet = sample_planar(reading, np.diag(sig**2), n_samples=n, rng=meet_rng)
    res.join_kind = map_a.update(f"A.x{c.a_steps}", f"B.x{c.b_start}", x_meet)
    say(f"rendezvous A.x{c.a_steps} -> B.x{c.b_start}: {res.join_kind}")
    res.scores.append(_score("joined: A's landmarks", map_a, scenario, "A.x0", 0, ("A",)))
    res.scores.append(_score("joined: B's landmarks", map_a, scenario, "A.x0", 0, ("B",)))

    if c.after_join_steps:
        robot_b.target = map_a
        frames = set(map_a.frames())

        def name(j: int) -> str:
            a_name = f"A.l{j}"
            return a_name if a_name in frames else f"B.l{j}"

        kinds = robot_b.drive(c.b_start + c.b_steps + c.after_join_steps, b_rng, name)
        res.cross_loop_closures = kinds.get("loop_closure:A", 0)
        say(f"robot B after the join: {kinds}")
        res.scores.append(_score("after loop closures: A's", map_a, scenario, "A.x0", 0,
                                 ("A",)))
        res.scores.append(_score("after loop closures: B's", map_a, scenario, "A.x0", 0,
                                 ("B",)))
    res.frames_a = len(map_a.frames())
    res.elapsed_s = time.perf_counter() - t0
    return res
