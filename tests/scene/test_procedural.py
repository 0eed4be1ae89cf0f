"""The procedural scene suite: seeded, valid on the virtual rig, covering the space it promises."""

import warnings

import pytest
import torch
import yaml

from torchproj.core import ConfigError
from torchproj.scene import load_scene, parse_scene
from torchproj.scene import procedural
from torchproj.scene.procedural import (KINDS, parse_suite_name, procedural_config, procedural_scene, suite_names,
                                        supersampling_for)
from torchproj.sim import VirtualRig

# Seeds the suite's code was not developed on (development used seed 0).
SEEDS = (5, 12)


def test_the_same_seed_gives_the_same_scene_and_another_seed_another():
    assert procedural_config(4, 2) == procedural_config(4, 2)
    assert procedural_config(4, 2) != procedural_config(5, 2)
    assert procedural_config(4, 2) != procedural_config(4, 3)
    # The config is plain YAML: written and read back, it parses to the same scene.
    data = procedural_config(4, 2)
    again = yaml.safe_load(yaml.safe_dump(data))
    assert again == data
    assert parse_scene(again).describe().splitlines()[1:] == procedural_scene(4, 2).describe().splitlines()[1:]


def test_suite_names_load_as_scenes():
    assert suite_names(3, 2) == ["suite-3-0", "suite-3-1"]
    assert suite_names(3, 1, "full", start=5) == ["suite-3-5-full"]
    assert parse_suite_name("suite-3-5-full") == (3, 5, "full")
    assert parse_suite_name("suite-3-x") is None and parse_suite_name("paper_two_planes") is None
    scene = load_scene("suite-3-1")
    assert scene.name == "suite-3-1"
    half = load_scene("suite-3-1", scale=0.5)
    assert half.camera.width == max(8, round(scene.camera.width * 0.5))


@pytest.mark.parametrize("bad, field", [(-1, "seed"), (1.5, "seed"), (True, "seed"), ("3", "seed"), (2 ** 64, "seed")])
def test_bad_seeds_are_refused_naming_the_field(bad, field):
    with pytest.raises(ConfigError, match=field):
        procedural_config(bad)
    with pytest.raises(ConfigError, match="index"):
        procedural_config(1, -2)
    with pytest.raises(ConfigError, match="size"):
        procedural_config(1, 0, "huge")


def test_a_suite_covers_the_space_it_promises():
    scenes = [procedural_scene(seed, i) for seed in SEEDS for i in range(24)]
    assert {parse_suite_name(s.name)[1] % len(KINDS) for s in scenes} == set(range(len(KINDS)))
    assert {len(s.projectors) for s in scenes} == {1, 2, 3, 4}
    assert len({(p.width, p.height) for s in scenes for p in s.projectors}) > 20  # projectors of many sizes
    assert {s.camera.channels for s in scenes} == {1, 3}
    assert any(len({a for surf in s.surfaces.values() for a in surf.albedo}) > 1 for s in scenes)  # tinted surfaces
    assert any(p.focus_distance is not None for s in scenes for p in s.projectors)
    assert {len(s.states) > 1 for s in scenes} == {True, False}
    assert any(len(s.targets) > 1 and len(s.states) == 1 for s in scenes)  # targets side by side
    types = {surf.type for s in scenes for surf in s.surfaces.values()}
    assert types == {"rectangle", "sphere", "cylinder", "box"}
    # Camera pixels from about half a cell to two cells across (a quarter to four cells of area).
    across = [max(p.fx for p in s.projectors) / s.camera.fx for s in scenes]
    assert min(across) < 0.6 and max(across) > 1.6
    assert {s.camera.supersampling for s in scenes} >= {2, 3, 4, 5, 6}
    for s in scenes:  # samples never too far apart for the cells (the rig would warn)
        assert s.camera.supersampling >= supersampling_for(max(p.fx for p in s.projectors), s.camera.fx)


# (55, 1): its first draw hid a plane behind another but for a 51 x 1 pixel strip.
@pytest.mark.parametrize("seed, index", [(SEEDS[i % 2], i) for i in range(8)] + [(55, 1)])
def test_every_target_is_seen_lit_and_unsaturated(seed, index):
    """On the virtual rig: no warning, each target's surfaces fill at least 100 camera pixels that a
    projector lights above the decoder's shadow threshold (40/255), and no projector's white
    saturates the camera on them."""
    scene = procedural_scene(seed, index)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the rig's checks of the samples, at its start and each state's cast
        rig = VirtualRig(scene)
        for spec in scene.target_specs():
            mask = rig.surface_mask(spec.state, spec.surfaces)
            black = rig.capture(spec.state, {}, noise=False, quantise=False)[0]
            lit = torch.zeros_like(mask)
            for j, p in enumerate(scene.projectors):
                white = rig.capture(spec.state, {j: torch.ones(1, 1, p.height, p.width)}, noise=False, quantise=False)[0]
                assert float(white[:, mask].max()) < 1.0, f"{scene.name}: projector {p.name} saturates {spec.name}"
                lit |= (white - black).mean(0) > 40 / 255
            assert int((mask & lit).sum()) >= 100, f"{scene.name}: target {spec.name} has {int((mask & lit).sum())} lit pixels"


def test_samples_resolve_the_cells_on_surfaces_seen_obliquely():
    """suite-55-11: a plane turned 37 degrees from the projector and 60 from the camera. The focal
    lengths ask for 4 samples a side (1.59-cell pixels), but on the plane the samples fall half a
    cell apart: with 4 the rig warns, naming 6; the generator gives the scene 6, and the rig's cast
    of every state then finds them within 0.4 cells."""
    from torchproj.scene.config import SAMPLE_SPACING
    from torchproj.sim.rig import sample_spacing

    data = procedural_config(55, 11)
    scene = parse_scene(data, name=data["name"])
    assert supersampling_for(max(p.fx for p in scene.projectors), scene.camera.fx) <= 4
    assert scene.camera.supersampling == 6
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rig = VirtualRig(scene)
        for state in scene.states:
            geo = rig.geometry(state.name)
            assert float(sample_spacing(geo.prj_xy, geo.surface_id, 6).max()) <= SAMPLE_SPACING
    coarse = parse_scene({**data, "camera": {**data["camera"], "supersampling": 4}}, name=data["name"])
    with pytest.warns(UserWarning, match=r"state 'near'.*camera.supersampling to 6"):
        VirtualRig(coarse).geometry("near")


def _rig_shares(data: dict) -> dict[str, float]:
    """Per target, the camera pixels whose centre sees its surfaces first over those that would
    with the state holding its surfaces alone, from the rig's full cast (one ray a pixel: the masks
    need no more, and the rig's warning that the cells need more is beside the point here)."""
    data = {**data, "camera": {**data["camera"], "supersampling": 1}}
    shares = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        whole = VirtualRig(parse_scene(data))
        for target in data["targets"]:
            seen = whole.surface_mask(target["state"], target["surfaces"])
            alone = {**data, "states": [{"name": target["state"], "surfaces": target["surfaces"]}],
                     "targets": [target]}
            every = VirtualRig(parse_scene(alone)).surface_mask(target["state"])
            shares[target["name"]] = int(seen.sum()) / int(every.sum())
    return shares


def test_a_draw_that_hides_a_target_is_drawn_again(monkeypatch):
    """The share of a target nothing hides, measured on a coarse grid of rays (2.4 pixels apart on
    suite-55-1's camera), is the rig's own to 0.05; the draw of suite-55-1 that hid plane1 (a share
    of 0.04) is refused, and the scene drawn instead shows every target."""
    monkeypatch.setattr(procedural, "_SEEN", 0.0)
    hidden = procedural_config(55, 1)
    monkeypatch.undo()
    kept = procedural_config(55, 1)
    for data in (hidden, kept, procedural_config(SEEDS[0], 5)):
        coarse, rig = procedural._seen_shares(data), _rig_shares(data)
        assert coarse.keys() == rig.keys()
        for name in rig:
            assert coarse[name] == pytest.approx(rig[name], abs=0.05), (data["name"], name)
    assert min(procedural._seen_shares(hidden).values()) < 0.1
    assert min(procedural._seen_shares(kept).values()) >= procedural._SEEN
    assert kept != {**hidden, "name": kept["name"]}
