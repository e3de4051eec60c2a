"""The ROS message -> constraint mapping (no ROS needed): conventions against hand-computed
cases, landmarks, keyframes, invalid messages, determinism of samples and request ids."""

from __future__ import annotations

import math

import numpy as np
import pytest
from mcsm.core.quat import qconj, qlog, qmul
from mcsm.viz import ros
from mcsm.viz.rosmsg import odometry, rosbags_maker
from mcsm_client.ros2.mapping import MappingError, MappingOptions, MessageMapper, order_key
from rosbags.typesys import Stores, get_typestore

MAKE = rosbags_maker(get_typestore(Stores.ROS2_KILTED))
S45 = math.sqrt(0.5)
YAW90 = np.array([1.0, 2.0, 0.0, S45, 0.0, 0.0, S45])  # x y z qw qx qy qz
#: ROS covariance: translation (0.01, 0.04, 0.09), rotation about X, Y, Z (4e-4, 1e-4, 9e-4),
#: and cov(x, rotation about Z) = 0.002
ROS_COV = np.diag([0.01, 0.04, 0.09, 4e-4, 1e-4, 9e-4])
ROS_COV[0, 5] = ROS_COV[5, 0] = 0.002


def msg(frame: str, child: str, mean: np.ndarray, cov: np.ndarray, t_ns: int = 5) -> object:
    return odometry(MAKE, t_ns, frame, child, mean, cov)


def test_ros_covariance_in_mcsm_chart_by_hand() -> None:
    # R̄ = Rz(90°): δb = R̄ᵀ δr turns rotation about world Y into body x and world X into
    # body -y, so their variances swap; z and cov(x, rz) stay.
    want = np.diag([0.01, 0.04, 0.09, 1e-4, 4e-4, 9e-4])
    want[0, 5] = want[5, 0] = 0.002
    got = ros.ros_cov_to_tangent(YAW90, ROS_COV)
    np.testing.assert_allclose(got, want, atol=1e-15)
    np.testing.assert_allclose(ros.tangent_cov_to_ros(YAW90, got), ROS_COV, atol=1e-15)
    # yaw-only covariance of a yaw-only pose: the same in both charts
    planar = np.diag([0.1, 0.2, 0.0, 0.0, 0.0, 0.3])
    np.testing.assert_allclose(ros.ros_cov_to_tangent(YAW90, planar), planar, atol=1e-15)


def test_pose_conversions() -> None:
    (p, q) = ros.pose_to_ros(YAW90)
    assert p == (1.0, 2.0, 0.0) and q == pytest.approx((0.0, 0.0, S45, S45))
    np.testing.assert_allclose(ros.pose_from_ros(p, q), YAW90)
    with pytest.raises(ValueError, match="zero"):
        ros.pose_from_ros((0, 0, 0), (0, 0, 0, 0))
    assert ros.frame_from_ros("/base_link", "robot1") == "robot1/base_link"
    with pytest.raises(ValueError):
        ros.frame_from_ros("base link")


def test_odometry_constraint_samples_follow_ros_conventions() -> None:
    """Samples of a constraint message: translation deviations in the header frame and
    rotation deviations about its fixed axes (log(q q̄⁻¹)) have ROS's covariance."""
    n = 20000
    (c,) = MessageMapper().map("/mcsm/constraints", msg("odom", "base", YAW90, ROS_COV), n)
    assert (c.kind, c.a, c.b, c.samples.shape) == ("constraint", "odom", "base", (n, 7))
    assert c.request_id.startswith("ros-constraint-") and len(c.request_id) == 47
    dt = c.samples[:, :3] - YAW90[:3]
    dr = qlog(qmul(c.samples[:, 3:], qconj(YAW90[3:])[None, :]))  # about the world axes
    got = np.cov(np.concatenate((dt, dr), axis=1), rowvar=False)
    sd = np.sqrt(np.diag(ROS_COV))
    np.testing.assert_allclose(got / np.outer(sd, sd), ROS_COV / np.outer(sd, sd), atol=0.03)
    np.testing.assert_allclose(c.samples[:, :3].mean(axis=0), YAW90[:3], atol=0.01)


def test_landmark_mapping() -> None:
    cov = np.full((6, 6), 99.0)  # rotation rows are ignored
    cov[:3, :3] = [[0.04, 0.01, 0.0], [0.01, 0.09, 0.0], [0.0, 0.0, 0.0]]
    (c,) = MessageMapper().map("/mcsm/landmarks",
                               msg("x1", "l7", np.array([3.0, -1.0, 0.5, 0.3, 0.1, 0.2, 0.9]),
                                   cov), 20000)
    assert (c.kind, c.a, c.b, c.samples.shape, c.is_point) == ("landmark", "x1", "l7",
                                                               (20000, 3), True)
    np.testing.assert_allclose(c.samples.mean(axis=0), [3.0, -1.0, 0.5], atol=0.01)
    assert np.all(c.samples[:, 2] == 0.5)  # no z variance: exact
    np.testing.assert_allclose(np.cov(c.samples[:, :2], rowvar=False), cov[:2, :2], rtol=0.05,
                               atol=0.002)


def test_samples_and_ids_come_from_the_message() -> None:
    m = msg("odom", "base", YAW90, ROS_COV, t_ns=7)
    (a,) = MessageMapper().map("/mcsm/constraints", m, 50)
    (b,) = MessageMapper().map("/mcsm/constraints", m, 50)
    assert a.request_id == b.request_id and np.array_equal(a.samples, b.samples)
    other_stamp = msg("odom", "base", YAW90, ROS_COV, t_ns=8)
    other_cov = msg("odom", "base", YAW90, ROS_COV * 1.0000001, t_ns=7)
    for m2 in (other_stamp, other_cov):
        (c,) = MessageMapper().map("/mcsm/constraints", m2, 50)
        assert c.request_id != a.request_id and not np.array_equal(c.samples, a.samples)
    # the same message on a landmark topic is another constraint (kind in the hash)
    (p,) = MessageMapper().map("/mcsm/landmarks", m, 50)
    assert p.request_id.startswith("ros-landmark-") and p.request_id[13:] != a.request_id[15:]
    # order: stamp, then odometry < constraint < landmark, then topic, then arrival
    assert order_key("/odom", "odometry", m, 9) < order_key("/a", "constraint", m, 1) < \
        order_key("/b", "landmark", m, 0) < order_key("/a", "odometry", other_stamp, 0)


def test_odometry_keyframes_by_hand() -> None:
    mapper = MessageMapper(MappingOptions(keyframe_distance_m=0.5, keyframe_angle_rad=0.5))
    cov0 = np.diag([0.01, 0.01, 0.0, 0.0, 0.0, 1e-4])
    (k0,) = mapper.map("/odom", msg("odom", "base_link", YAW90, cov0, 1), 2000)
    assert (k0.a, k0.b, k0.kind) == ("odom", "base_link.0", "odometry")
    np.testing.assert_allclose(k0.samples[:, :3].mean(axis=0), YAW90[:3], atol=0.01)
    # 0.1 m further along the robot's heading (world +y): no keyframe
    p1 = YAW90.copy()
    p1[1] += 0.1
    assert mapper.map("/odom", msg("odom", "base_link", p1, cov0 * 1.1, 2), 2000) == []
    # 0.6 m along its heading and 10° more yaw: the increment base_link.0 -> base_link.1 is
    # 0.6 m straight ahead in base_link.0's frame; its covariance is the growth, turned into
    # base_link.0's axes: world x <-> body y
    yaw = math.radians(100.0)
    p2 = np.array([1.0, 2.6, 0.0, math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])
    cov2 = cov0 + np.diag([0.04, 0.0, 0.0, 0.0, 0.0, 4e-4])  # grew in world x and yaw
    (k1,) = mapper.map("/odom", msg("odom", "base_link", p2, cov2, 3), 20000)
    assert (k1.a, k1.b) == ("base_link.0", "base_link.1")
    from mcsm.core import mean_and_cov

    mean, cov = mean_and_cov(k1.samples)
    np.testing.assert_allclose(mean[:3], [0.6, 0.0, 0.0], atol=0.01)
    np.testing.assert_allclose(mean[3:], [math.cos(math.radians(5)), 0, 0,
                                          math.sin(math.radians(5))], atol=1e-3)
    np.testing.assert_allclose(np.diag(cov), [0.0, 0.04, 0.0, 0.0, 0.0, 4e-4], rtol=0.05,
                               atol=1e-6)
    # a landmark seen from base_link after odometry that made no keyframe: that odometry
    # becomes keyframe base_link.2 first, and the landmark hangs from it
    p3 = p2.copy()
    p3[1] += 0.05
    assert mapper.map("/odom", msg("odom", "base_link", p3, cov2, 4), 100) == []
    kf, lm = mapper.map("/mcsm/landmarks", msg("base_link", "tree", YAW90, cov0, 5), 100)
    assert (kf.a, kf.b, lm.a, lm.b) == ("base_link.1", "base_link.2", "base_link.2", "tree")
    assert mapper.keyframe_name("base_link") == "base_link.2"


def test_keyframe_increment_ids_shrinking_covariance_and_prefix() -> None:
    """A keyframe increment's id depends on both its messages; a covariance that shrank
    between keyframes gives an increment with none (negative growth clipped to 0, not an
    error); ``frame_prefix`` names the mapper's frames."""
    from mcsm.core import mean_and_cov

    cov0 = np.diag([0.01, 0.01, 0.0, 0.0, 0.0, 1e-4])
    far = YAW90.copy()
    far[1] += 1.0

    def increment(first: np.ndarray, second: np.ndarray, prefix: str = "") -> object:
        m = MessageMapper(MappingOptions(frame_prefix=prefix))
        m.map("/odom", msg("odom", "base_link", YAW90, first, 1), 200)
        (k1,) = m.map("/odom", msg("odom", "base_link", far, second, 2), 200)
        return k1

    a, b = increment(cov0, 2 * cov0), increment(1.5 * cov0, 2 * cov0)
    assert a.request_id != b.request_id  # type: ignore[attr-defined]
    shrunk = increment(2 * cov0, cov0)
    _, cov = mean_and_cov(shrunk.samples)  # type: ignore[attr-defined]
    np.testing.assert_allclose(cov, 0.0, atol=1e-12)
    named = increment(cov0, 2 * cov0, prefix="robot1")
    assert (named.a, named.b) == ("robot1/base_link.0",  # type: ignore[attr-defined]
                                  "robot1/base_link.1")


INDEFINITE = np.eye(6)  # symmetric, no negative variance, but an eigenvalue of -1
INDEFINITE[0, 1] = INDEFINITE[1, 0] = 2.0


@pytest.mark.parametrize("frame,child,cov,why", [
    ("odom", "odom", ROS_COV, "both"),
    ("odom", "base link", ROS_COV, "frame id"),
    ("odom", "base", np.diag([-1.0, 1, 1, 1, 1, 1]), "negative variance"),
    ("odom", "base", np.diag([1.0, 1, 1, 1, 1, 1]) + np.eye(6, k=1), "symmetric"),
    ("odom", "base", INDEFINITE, "semi-definite"),
])
def test_invalid_messages(frame: str, child: str, cov: np.ndarray, why: str) -> None:
    with pytest.raises(MappingError, match=why):
        MessageMapper().map("/mcsm/constraints", msg(frame, child, YAW90, cov), 10)


def test_markers_use_the_plot_ellipse() -> None:
    """The region markers are mcsm.viz.scene's 95 % ellipse (what mcsm plot draws)."""
    from mcsm.viz.scene import ellipse

    cov = np.diag([0.04, 0.01, 0.0, 0.0, 0.0, 0.0])
    cov[0, 1] = cov[1, 0] = 0.01
    f = ros.PlacedFrame("l1", "map", True, np.array([2.0, 1.0, 0, 1, 0, 0, 0]), cov, 1)
    specs = ros.map_markers([f])
    assert specs[0].kind == "deleteall"
    disc, label = specs[1], specs[2]
    e = ellipse([2.0, 1.0], cov[:2, :2])
    assert disc.kind == "cylinder" and disc.scale[:2] == pytest.approx((e.width, e.height))
    yaw = 2 * math.atan2(disc.orientation_xyzw[2], disc.orientation_xyzw[3])
    assert math.degrees(yaw) == pytest.approx(e.angle_deg)
    assert (label.kind, label.text, label.id) == ("text", "l1", disc.id)
