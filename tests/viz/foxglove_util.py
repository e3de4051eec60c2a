"""Decode Foxglove protobuf messages from the schema a file or a server advertises, with the
``protobuf`` package alone (no foxglove-sdk code), and the expected 95 % ellipsoids."""

from __future__ import annotations

from typing import Any

import numpy as np
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from scipy.spatial.transform import Rotation
from scipy.stats import chi2


def message_class(schema_name: str, file_descriptor_set: bytes) -> Any:
    """The protobuf message class named ``schema_name`` from a serialized FileDescriptorSet."""
    fds = descriptor_pb2.FileDescriptorSet.FromString(file_descriptor_set)
    pool = descriptor_pool.DescriptorPool()
    pending = list(fds.file)
    for _ in range(len(pending) + 1):  # add files once their dependencies are in
        left = []
        for fd in pending:
            try:
                pool.Add(fd)
            except TypeError:
                left.append(fd)
        pending = left
        if not pending:
            break
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


def check_scene_against_map(scene: Any, m: Any) -> dict[str, Any]:
    """Assert that a decoded ``foxglove.SceneUpdate`` shows map ``m``: one entity per frame in
    its root frame, the sphere at the sample mean, its size and orientation those of the 95 %
    ellipsoid of the sample covariance (computed here with numpy/scipy: χ² with as many
    degrees of freedom as the covariance spans, 2 for a planar map). Returns the entities by
    frame name."""
    ents = {e.id[len("frame/"):]: e for e in scene.entities if e.id.startswith("frame/")}
    want = {f: r for r in m.components() for f in m.component(r)}
    assert set(ents) == set(want)
    assert len(scene.deletions) == 1 and scene.deletions[0].type == 1  # ALL, then the entities
    for name, root in want.items():
        e = ents[name]
        assert e.frame_id == root
        xyz = m.query(root, name)[:, :3]
        cov = np.cov(xyz.T)
        (sphere,) = e.spheres
        p = sphere.pose.position
        np.testing.assert_allclose([p.x, p.y, p.z], xyz.mean(axis=0), rtol=1e-12, atol=1e-12)
        shown = np.array([sphere.size.x, sphere.size.y, sphere.size.z])
        lam = np.clip(np.linalg.eigvalsh(cov), 0, None)
        lam[lam <= 1e-12 * lam.max()] = 0.0
        k = chi2.ppf(0.95, max(1, int(np.count_nonzero(lam))))
        true = 2 * np.sqrt(k * lam)
        # drawn with a thickness of at least 1 % of the largest axis (a flat disc is lit)
        np.testing.assert_allclose(np.sort(shown), np.maximum(true, 0.01 * true.max()),
                                   rtol=1e-9, atol=1e-12, err_msg=name)
        sizes = np.where(shown > 0.01 * true.max() * (1 + 1e-9), shown, true[0])
        o = sphere.pose.orientation
        r = Rotation.from_quat([o.x, o.y, o.z, o.w]).as_matrix()
        rebuilt = r @ np.diag((sizes / 2) ** 2 / k) @ r.T
        np.testing.assert_allclose(rebuilt, cov, rtol=1e-8, atol=1e-12, err_msg=name)
        # the unlit outline: a loop on the region's boundary, in a saturated colour
        (ring,) = e.lines
        pts = np.array([[q.x, q.y, q.z] for q in ring.points]) - xyz.mean(axis=0)
        d2 = np.einsum("ni,ij,nj->n", pts, np.linalg.pinv(cov, rcond=1e-9), pts)
        if lam.max() > 0:  # (a root frame has no spread: its region is its point)
            np.testing.assert_allclose(d2, k, rtol=1e-6, err_msg=name)  # on the boundary
        rgb = np.array([ring.color.r, ring.color.g, ring.color.b])
        assert ring.color.a == 1.0 and rgb.max() - rgb.min() > 0.3, (name, rgb)  # no grey
        rgb = np.array([sphere.color.r, sphere.color.g, sphere.color.b])
        assert rgb.max() - rgb.min() > 0.3, (name, rgb)
        if e.texts:
            assert e.texts[0].text == name
    return ents
