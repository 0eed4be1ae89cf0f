"""Geometric weighting from calibrated correspondences against the simulator's exact geometry."""

import math

import pytest
import torch

from torchproj.calib import calibrate_projector
from torchproj.pipeline import simulate_calibration
from torchproj.core import InputError
from torchproj.sim import VirtualRig
from torchproj.transport import StateCalibration, Target, build_transport, geometric_weights, point_map

from ..helpers import small_scene


@pytest.fixture(scope="module")
def head():
    scene = small_scene("head_two_positions", camera=(320, 240), projector=(256, 192))
    rig = VirtualRig(scene)
    pcs = [calibrate_projector(simulate_calibration(rig, "position1", j), (256, 192)) for j in range(2)]
    return scene, rig, pcs


def test_triangulated_points_match_the_surface(head):
    scene, rig, pcs = head
    points = point_map([c.prj_xy for c in pcs], scene.camera, scene.projectors)
    truth = rig.geometry("position1").points.double()
    both = torch.isfinite(points).all(-1) & torch.isfinite(truth).all(-1)
    assert int(both.sum()) > 5000
    err = (points[both] - truth[both]).norm(dim=-1)
    assert float(err.median()) < 0.5e-3  # metres, on a curved head at 0.8 m


def test_weights_follow_the_true_falloff_and_angle(head):
    scene, rig, pcs = head
    geo = rig.geometry("position1")
    weights = geometric_weights([c.prj_xy for c in pcs], scene.camera, scene.projectors)
    # The skull away from the nose, the neck and the silhouette: normals from a smoothed point map
    # cannot follow creases.
    skull = (geo.surface_id == 0).float()[None, None]
    interior = -torch.nn.functional.max_pool2d(-skull, 9, 1, 4)[0, 0] > 0.5
    for j, proj in enumerate(scene.projectors):
        to = torch.as_tensor(proj.centre) - geo.points.double()
        dist = to.norm(dim=-1)
        true = ((geo.normals.double() * to).sum(-1) / dist).clamp_min(0) / dist**2
        sel = interior & (weights[j] > 0) & torch.isfinite(true) & (true > 0.2 * float(true[torch.isfinite(true)].max()))
        ratio = weights[j][sel].double() / true[sel]
        assert int(sel.sum()) > 3000
        assert float(ratio.median()) == pytest.approx(1.0, abs=0.02)  # normals from a smoothed point map
        assert float((ratio - 1).abs().quantile(0.9)) < 0.05


def test_radiometric_is_geometric_times_the_light_budget(head):
    """White minus black = exposure * albedo / pi * power * vignetting * cos / d^2: the two weightings
    must differ by exactly that factor, pixel by pixel."""
    scene, _, pcs = head
    radiometric = StateCalibration.from_calibrations(pcs)
    geometric = StateCalibration.from_calibrations(pcs, "geometric", scene.camera, scene.projectors)
    albedo = scene.surfaces["head_near"].albedo[0]
    for j, proj in enumerate(scene.projectors):
        sel = (geometric.weight[j] > 0) & (radiometric.weight[j] > 0.1)
        ratio = radiometric.weight[j][sel] / geometric.weight[j][sel]
        budget = scene.camera.exposure * albedo / math.pi * proj.power * proj.response_a
        # Vignetting dims the cells by up to `vignetting` away from the centre.
        assert budget * (1 - proj.vignetting) * 0.97 < float(ratio.median()) < budget * 1.03
    img = torch.rand(1, 12, 12, generator=torch.Generator().manual_seed(0))
    ops = [build_transport({"position1": c}, [Target("position1", img, name="mask")], merge=False)
           for c in (radiometric, geometric)]
    # Geometric weighting loses the pixels near depth edges, where no normal can be estimated.
    cells = [set((ops[i].column_projector * 10**6 + ops[i].column_cell).tolist()) for i in range(2)]
    assert cells[1] <= cells[0] and len(cells[1]) > 0.85 * len(cells[0])


def test_geometric_weighting_needs_the_rig(head):
    _, _, pcs = head
    with pytest.raises(InputError, match="needs the camera and projectors"):
        StateCalibration.from_calibrations(pcs, "geometric")
    with pytest.raises(InputError, match="weighting must be"):
        StateCalibration.from_calibrations(pcs, "optical")
