"""Analytic ray casting in torch against Embree on tessellated meshes of the same shapes."""

import numpy as np
import pytest
import torch
import trimesh

from torchproj.scene import Surface, rotation_from_euler_deg
from torchproj.sim import make_caster


def _pose(position, euler=(0, 0, 0)):
    pose = np.eye(4)
    pose[:3, :3] = rotation_from_euler_deg(np.array(euler))
    pose[:3, 3] = position
    return pose


def _rays(n=4000, seed=0):
    """Rays from near the origin towards a 0.4 m wide region around (0, 0, 1)."""
    g = torch.Generator().manual_seed(seed)
    origins = (torch.rand(n, 3, generator=g) - 0.5) * 0.05
    targets = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([0.4, 0.4, 0.3]) + torch.tensor([0, 0, 1.0])
    d = torch.nn.functional.normalize(targets - origins, dim=-1)
    return origins, d


CASES = {
    "sphere": (dict(type="sphere", radii=(0.1, 0.1, 0.1)), lambda: trimesh.creation.icosphere(6, radius=0.1)),
    "ellipsoid": (dict(type="sphere", radii=(0.08, 0.12, 0.1)),
                  lambda: trimesh.creation.icosphere(6, radius=1.0).apply_scale([0.08, 0.12, 0.1])),
    "box": (dict(type="box", size=(0.2, 0.15, 0.1)), lambda: trimesh.creation.box(extents=(0.2, 0.15, 0.1))),
    "cylinder": (dict(type="cylinder", radius=0.06, height=0.2),
                 # trimesh's cylinder runs along z; ours along y.
                 lambda: trimesh.creation.cylinder(radius=0.06, height=0.2, sections=512).apply_transform(
                     trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_analytic_matches_embree(tmp_path, name):
    kwargs, make_mesh = CASES[name]
    pose = _pose([0.02, -0.01, 1.0], (15, 30, -10))
    analytic = make_caster(Surface(name=name, world_from_local=pose, **kwargs))
    path = tmp_path / f"{name}.ply"
    make_mesh().export(path)
    mesh = make_caster(Surface(name=name, type="mesh", world_from_local=pose, mesh_file=path))
    o, d = _rays()
    t_a, n_a = analytic.hit(o, d)
    t_m, n_m = mesh.hit(o, d)
    hit_a, hit_m = torch.isfinite(t_a), torch.isfinite(t_m)
    assert hit_a.sum() > 300  # the test must actually hit the shape
    # Tessellation moves silhouettes by micrometres: rays may disagree only at grazing angles.
    assert (hit_a != hit_m).float().mean() < 0.01
    both = hit_a & hit_m
    assert torch.allclose(t_a[both], t_m[both], atol=2e-4)
    # Normals agree up to orientation (the rig turns them towards the viewer).
    cos = (n_a[both] * n_m[both]).sum(-1).abs()
    assert float(cos.median()) > 0.999


def test_rectangle_bounds_and_plane():
    pose = _pose([0, 0, 1.0])
    o = torch.zeros(3, 3)
    d = torch.nn.functional.normalize(torch.tensor([[0.0, 0, 1], [0.09, 0, 1], [0.11, 0, 1]]), dim=-1)
    rect = make_caster(Surface(name="r", type="rectangle", world_from_local=pose, size=(0.2, 0.2)))
    t, n = rect.hit(o, d)
    assert torch.isfinite(t).tolist() == [True, True, False]
    assert float(t[0]) == pytest.approx(1.0)
    plane = make_caster(Surface(name="p", type="plane", world_from_local=pose))
    t, _ = plane.hit(o, d)
    assert torch.isfinite(t).all()


def test_hits_behind_the_origin_are_ignored():
    sphere = make_caster(Surface(name="s", type="sphere", world_from_local=_pose([0, 0, -1.0]), radii=(0.1,) * 3))
    t, _ = sphere.hit(torch.zeros(1, 3), torch.tensor([[0.0, 0, 1]]))
    assert torch.isinf(t).all()


def test_ray_starting_inside_a_box_hits_its_far_wall():
    box = make_caster(Surface(name="b", type="box", world_from_local=_pose([0, 0, 0]), size=(2.0, 2.0, 2.0)))
    t, n = box.hit(torch.zeros(1, 3), torch.tensor([[0.0, 0, 1]]))
    assert float(t[0]) == pytest.approx(1.0)
    assert n[0].abs().tolist() == [0, 0, 1]


def test_a_mesh_surface_is_cast_by_the_rig_as_its_analytic_shape(tmp_path):
    """The rig casts rays for a capture of moving surfaces (and for the light check before every
    calibration) from one camera origin, (1, 3) against (N, 3) directions: the mesh caster sized its
    results by the origins, and every run of a scene with a mesh stopped at an IndexError. An
    icosphere seen through the rig lands, and is lit, where the analytic sphere is."""
    from torchproj.scene import parse_scene
    from torchproj.sim import VirtualRig

    trimesh.creation.icosphere(5, radius=0.1).export(tmp_path / "ball.ply")

    def rig(surface):
        return VirtualRig(parse_scene({
            "name": "ball", "projectors": [{"name": "p", "resolution": [128, 96], "focal": 192,
                                            "pose": {"position": [0.05, 0, 0], "look_at": [0, 0, 0.8]}}],
            "camera": {"resolution": [160, 120], "focal": 400, "supersampling": 2,
                       "pose": {"position": [-0.05, 0, 0], "look_at": [0, 0, 0.8]}},
            "surfaces": {"ball": {**surface, "pose": {"position": [0, 0, 0.8]}}},
            "states": [{"name": "s", "surfaces": ["ball"]}]}))

    mesh, sphere = rig({"type": "mesh", "file": str(tmp_path / "ball.ply")}), rig({"type": "sphere", "radius": 0.1})
    m, s = mesh.geometry("s"), sphere.geometry("s")
    seen_m, seen_s = m.surface_id >= 0, s.surface_id >= 0
    assert int(seen_s.sum()) > 2000 and float((seen_m != seen_s).float().mean()) < 0.01
    both = seen_m & seen_s
    apart = (m.points[both] - s.points[both]).norm(dim=-1)  # the tessellation's, metres; most at the outline
    assert float(apart.median()) < 1e-4 and float(apart.quantile(0.99)) < 1e-3
    lit = torch.isfinite(m.prj_xy[0]).all(-1) & torch.isfinite(s.prj_xy[0]).all(-1)
    assert float((m.prj_xy[0][lit] - s.prj_xy[0][lit]).norm(dim=-1).median()) < 0.05  # cells
    white = {0: torch.ones(1, 1, 96, 128)}
    shot_m, shot_s = (r.capture_surfaces(list(r.scene.surfaces.values()), white, None, noise=False)[0]
                      for r in (mesh, sphere))
    assert float((shot_m - shot_s).abs().median()) < 2 / 255 and float(shot_s.max()) > 0.3
