"""Scoring patterns on the virtual rig against an independent computation of the same scores."""

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from torchproj.core import InputError
from torchproj.pipeline import evaluate_patterns, scene_targets, target_image
from torchproj.solve import ProjectionModel
from torchproj.transport import target_on_camera


def test_scores_are_psnr_and_scikit_image_ssim_of_the_capture(quarter_rig):
    scene, cal = quarter_rig
    targets = scene_targets(scene, rig=cal.rig)
    model = ProjectionModel.from_calibration(cal, targets)
    patterns = model.to_patterns()
    ev = evaluate_patterns(cal, patterns, targets, scale=model.scale, noise=False)
    shown = {j: (p.float() / 255)[None] for j, p in enumerate(patterns)}
    for t, score in zip(targets, ev.targets):
        shot = cal.rig.capture(t.state, shown, noise=False)[0]
        torch.testing.assert_close(ev.captures[t.state], shot)
        values, covered = target_on_camera(t, cal.states[t.state].lit())
        est = ((shot - cal.black[t.state]) / model.scale).clamp(0, 1)
        mse = float(((est[:, covered].double() - values[:, covered].double()) ** 2).mean())
        assert score.psnr_db == pytest.approx(10 * np.log10(1 / mse), abs=1e-9)
        ys, xs = torch.nonzero(covered, as_tuple=True)
        box = (slice(int(ys.min()), int(ys.max()) + 1), slice(int(xs.min()), int(xs.max()) + 1))
        _, ssim_map = structural_similarity(est[0][box].double().numpy(), values[0][box].double().numpy(),
                                            data_range=1.0, full=True)
        assert score.ssim == pytest.approx(float(ssim_map[covered[box].numpy()].mean()), abs=1e-9)
        assert score.pixels == int(covered.sum()) and 0 <= score.crosstalk <= 1


def test_a_seed_gives_every_set_of_patterns_the_same_noise(quarter_rig):
    """Scored with a seed, the same patterns get the same captures whatever was captured before, the
    noise of the rig's own capture with that seed (state k: seed + k); another seed draws other
    noise; without one, the rig's generator draws on."""
    scene, cal = quarter_rig
    targets = scene_targets(scene, rig=cal.rig)
    model = ProjectionModel.from_calibration(cal, targets)
    patterns = model.to_patterns()
    first = evaluate_patterns(cal, patterns, targets, scale=model.scale, paper=False, seed=11)
    evaluate_patterns(cal, patterns, targets, scale=model.scale, paper=False)  # draws from the generator
    again = evaluate_patterns(cal, patterns, targets, scale=model.scale, paper=False, seed=11)
    other = evaluate_patterns(cal, patterns, targets, scale=model.scale, paper=False, seed=12)
    shown = {j: (p.float() / 255)[None] for j, p in enumerate(patterns)}
    for k, state in enumerate(dict.fromkeys(t.state for t in targets)):
        assert torch.equal(first.captures[state], again.captures[state])
        torch.testing.assert_close(first.captures[state], cal.rig.capture(state, shown, seed=11 + k)[0])
        assert not torch.equal(first.captures[state], other.captures[state])
    assert [s.psnr_db for s in first.targets] == [s.psnr_db for s in again.targets]
    unseeded = [evaluate_patterns(cal, patterns, targets, scale=model.scale, paper=False) for _ in range(2)]
    assert not torch.equal(*(e.captures[targets[0].state] for e in unseeded))
    for bad in (-1, 1.5, True, "7", 2 ** 70):
        with pytest.raises(InputError, match="seed must be a whole number"):
            evaluate_patterns(cal, patterns, targets, scale=model.scale, paper=False, seed=bad)


def test_other_images_score_worse_on_the_same_patterns(quarter_rig):
    scene, cal = quarter_rig
    targets = scene_targets(scene, rig=cal.rig)
    model = ProjectionModel.from_calibration(cal, targets)
    swapped = scene_targets(scene, [target_image("coffee", 1), target_image("rocket", 1)], rig=cal.rig)
    right = evaluate_patterns(cal, model.to_patterns(), targets, scale=model.scale, noise=False).targets
    wrong = evaluate_patterns(cal, model.to_patterns(), swapped, scale=model.scale, noise=False).targets
    for a, b in zip(right, wrong):
        assert a.ssim > b.ssim + 0.2 and a.psnr_db > b.psnr_db + 3


def test_patterns_for_another_rig_are_refused(quarter_rig):
    scene, cal = quarter_rig
    with pytest.raises(InputError, match="one pattern per projector"):
        evaluate_patterns(cal, [torch.zeros(1, 192, 256, dtype=torch.uint8)], scene_targets(scene, rig=cal.rig),
                          scale=0.5)


@pytest.mark.parametrize("as_given, says", [
    (lambda p: p.long(), "must be uint8 .* or float light in \\[0, 1\\], got torch.int64"),
    (lambda p: p.float(), r"must lie in \[0, 1\], got values in \[0, 255\]"),
    (lambda p: p > 128, "got torch.bool"),
    (lambda p: p.float().fill_(float("nan")), "non-finite"),
    (lambda p: p.numpy(), "must be a torch.Tensor, got ndarray"),
])
def test_patterns_of_levels_in_another_type_are_refused_not_shown_as_white(quarter_rig, as_given, says):
    """Levels 0-255 in int64 or float were taken as light 0-255: every cell white, 4 dB."""
    scene, cal = quarter_rig
    targets = scene_targets(scene, rig=cal.rig)
    model = ProjectionModel.from_calibration(cal, targets)
    patterns = model.to_patterns()
    patterns[1] = as_given(patterns[1])
    with pytest.raises(InputError, match=r"patterns\[1\] .*" + says):
        evaluate_patterns(cal, patterns, targets, scale=model.scale)


def test_targets_of_another_camera_or_kind_are_named_and_a_numpy_seed_is_a_seed(quarter_rig):
    """A mask of another camera raised torch's size mismatch, one Target 'not iterable', a numpy seed
    was refused while the rig takes it, and a scale of '1' raised a TypeError."""
    import dataclasses

    scene, cal = quarter_rig
    targets = scene_targets(scene, rig=cal.rig)
    model = ProjectionModel.from_calibration(cal, targets)
    patterns = model.to_patterns()
    other = [dataclasses.replace(targets[0], mask=torch.ones(10, 10, dtype=torch.bool)), targets[1]]
    # A colour image on this grey camera ended, after the captures, in "estimate must have shape (3, ...)".
    colour = [dataclasses.replace(t, image=t.image.expand(3, -1, -1)) for t in targets]
    # patterns of None ended in len()'s TypeError, states that are no dict of the targets' states in
    # indexing errors or a KeyError.
    for given, options, says in [(other, {}, "'near' mask must have shape"), (targets[0], {}, "list of Target"),
                                 (targets, {"scale": "1"}, "scale must be a finite number > 0"),
                                 (colour, {}, r"target 'near' has 3 channel\(s\) and the camera 1: give every target "
                                              r"the camera's \(torchproj.pipeline.image_with_channels"),
                                 ([dataclasses.replace(targets[0], image=[[0.5] * 8] * 8), targets[1]], {},
                                  "target 'near' image must be a torch.Tensor, got list"),
                                 (targets, {"states": [1]}, "states must be a dict of state name -> StateCalibration, got list"),
                                 (targets, {"states": {}}, r"no calibration of the targets' states \['far', 'near'\]; calibrated: \[\]"),
                                 (targets, {"patterns": None}, r"patterns must be a list of one image per projector \(2\), got NoneType")]:
        with pytest.raises(InputError, match=says):
            evaluate_patterns(cal, **{"patterns": patterns, "targets": given, "scale": model.scale, **options})
    by_numpy = evaluate_patterns(cal, patterns, targets, scale=model.scale, seed=np.int64(4)).targets
    by_int = evaluate_patterns(cal, patterns, targets, scale=model.scale, seed=4).targets
    assert [t.psnr_db for t in by_numpy] == [t.psnr_db for t in by_int]


def test_ghost_images_follow_the_light_to_where_parallax_puts_it(quarter_rig):
    """One projector shows a picture; the simulator renders it on the far plane and on the near one.
    Carried from the far capture through the calibrated correspondences, the picture must reproduce
    the near capture (the physics is the independent reference), where the same camera pixels of
    the far capture do not: parallax shifts it."""
    from skimage.data import astronaut
    from skimage.transform import resize

    from torchproj.metrics import explained_share
    from torchproj.pipeline import ghost_images

    scene, cal = quarter_rig
    near, far = scene_targets(scene, None, cal.rig)
    proj = scene.projectors[0]
    picture = torch.from_numpy(resize(astronaut().mean(-1) / 255, (proj.height, proj.width))).float()
    light = {s: (cal.rig.capture(s, {0: picture[None, None]}, noise=False)[0] - cal.black[s]).cpu()
             for s in ("near", "far")}
    lit = {s: cal.states[s].lit() for s in ("near", "far")}
    on_camera = [(light["near"], lit["near"]), (light["far"], lit["far"])]
    ghosts = ghost_images(cal.states, [near, far], on_camera)[0]  # on the near target
    assert len(ghosts) == 2  # one per projector; the second carries the picture through the other's cells
    carried = explained_share(light["near"], ghosts[:1], lit["near"])
    in_place = explained_share(light["near"], [light["far"]], lit["near"] & lit["far"])
    assert carried > 0.9 and in_place < carried - 0.4


def test_affine_psnr_takes_brightness_out_and_nothing_else():
    from torchproj.pipeline import affine_psnr
    from torchproj.metrics import psnr

    g = torch.Generator().manual_seed(0)
    values = torch.rand(1, 30, 40, generator=g)
    covered = torch.ones(30, 40, dtype=torch.bool)
    covered[:5] = False
    assert affine_psnr(0.5 * values + 0.2, values, covered) > 100  # a pure gain and offset costs nothing
    noisy = values + 0.1 * torch.randn(values.shape, generator=g)
    assert affine_psnr(noisy, values, covered) >= psnr(noisy[:, covered], values[:, covered])  # gain 1, offset 0 is a candidate
    assert affine_psnr(torch.rand(1, 30, 40, generator=g), values, covered) < 12  # structure is not forgiven


def test_paper_score_compares_with_a_direct_single_projector_capture(quarter_rig):
    """The paper's baseline, built here by hand: the target image on the cells of the projector that sees
    most of it (each cell the mean over the camera pixels decoded to it), response-compensated, projected
    alone. Shown as the patterns, it must score as a perfect match against the paper's reference."""
    from torchproj.core.conventions import round_to_pixel
    from torchproj.solve import compensate

    scene, cal = quarter_rig
    targets = scene_targets(scene, rig=cal.rig)
    model = ProjectionModel.from_calibration(cal, targets)
    target = targets[0]
    values, covered = target_on_camera(target, cal.states[target.state].lit())
    light, counts = [], []
    for j, (w, h) in enumerate(cal.states[target.state].projector_sizes):
        xy = cal.states[target.state].prj_xy[j].reshape(-1, 2)
        ok = covered.reshape(-1) & torch.isfinite(xy).all(-1)
        cell = round_to_pixel(xy[ok])
        inside = (cell[:, 0] >= 0) & (cell[:, 0] < w) & (cell[:, 1] >= 0) & (cell[:, 1] < h)
        flat = (cell[inside, 1] * w + cell[inside, 0]).numpy()
        v = values.reshape(-1)[ok][inside].double().numpy()
        sums, count = np.bincount(flat, v, w * h), np.bincount(flat, minlength=w * h)
        light.append(torch.from_numpy(np.where(count > 0, sums / np.maximum(count, 1), 0.0)).float().reshape(1, h, w))
        counts.append(int(inside.sum()))
    j = int(np.argmax(counts))
    patterns = [torch.zeros(1, h, w, dtype=torch.uint8) for w, h in cal.states[target.state].projector_sizes]
    patterns[j] = compensate([light[j]], [cal.responses[j]])[0]
    score = evaluate_patterns(cal, patterns, targets, scale=model.scale, noise=False).targets[0]
    assert score.paper["psnr_db"] > 60 and score.paper["ssim"] == pytest.approx(1.0, abs=1e-9)
    # The solver's patterns are further from that baseline than the baseline is from itself.
    solved = evaluate_patterns(cal, model.to_patterns(), targets, scale=model.scale, noise=False).targets[0]
    assert 5 < solved.paper["psnr_db"] < 40 and solved.paper["ssim"] < 0.99
    assert solved.affine_psnr_db >= solved.psnr_db
    assert "paper" not in evaluate_patterns(cal, model.to_patterns(), targets, scale=model.scale, noise=False,
                                            paper=False).targets[0].as_dict()


def test_a_target_image_of_one_pixel_is_refused_naming_it(tmp_path):
    from torchproj.core import write_image

    write_image(tmp_path / "dot.png", torch.full((1, 1, 1), 0.5))
    with pytest.raises(InputError, match=r"dot.png': 1x1 pixels; .* needs at least 2 x 2"):
        target_image(str(tmp_path / "dot.png"), 1)
    write_image(tmp_path / "pair.png", torch.full((1, 2, 2), 0.5))
    assert target_image(str(tmp_path / "pair.png"), 3).shape == (3, 2, 2)


@pytest.mark.parametrize("level", [0.0, 1.0])
def test_a_constant_target_is_warned_about_and_its_report_row_says_why(quarter_rig, tmp_path, level):
    """A white target was not warned about: the warp blended its outline with the black outside it, and
    the pixels there, up to 0.1% darker, made it more than one value."""
    import json
    import math

    from torchproj.core import write_json

    scene, cal = quarter_rig
    images = [torch.full((1, 30, 40), level), target_image("camera", 1)]
    targets = scene_targets(scene, images, rig=cal.rig)
    model = ProjectionModel.from_calibration(cal, targets)
    with pytest.warns(UserWarning, match=r"target '.*': its image is one value over its \d+ pixels") as caught:
        ev = evaluate_patterns(cal, model.to_patterns(), targets, scale=model.scale, noise=False, paper=False)
    assert len(caught) == 1  # the detailed target is not warned about
    dark, detailed = ev.targets
    assert dark.constant_target and not detailed.constant_target and detailed.notes() == {}
    assert math.isinf(dark.affine_psnr_db)  # a gain and offset reproduce a constant exactly
    write_json(tmp_path / "r.json", [s.as_dict() for s in ev.targets])
    rows = json.loads((tmp_path / "r.json").read_text())
    assert rows[0]["affine_psnr_db"] is None and "one value" in rows[0]["notes"]["target"]
    assert "notes" not in rows[1]
    # A capture equal to its target: the infinite PSNR is null in JSON, with the reason beside it.
    perfect = type(dark)(name="p", state=dark.state, psnr_db=math.inf, ssim=1.0, crosstalk=0.0, pixels=4,
                         estimate=detailed.values, values=detailed.values, covered=detailed.covered,
                         affine_psnr_db=math.inf)
    assert set(perfect.notes()) == {"psnr_db", "affine_psnr_db"}


def test_image_tensors_take_the_cameras_channels_as_files_do(quarter_rig):
    """run_virtual's and scene_targets' image tensors of the other channel count went through
    calibration and the solve, to end in the scores' shape error; they are read as a file of them is:
    colour by its luminance on a grey camera (scikit-image's rgb2gray, to rounding), grey repeated."""
    from skimage.color import rgb2gray

    from torchproj.pipeline import image_with_channels

    scene, cal = quarter_rig
    colour = [target_image(name, 3) for name in ("astronaut", "coffee")]
    targets = scene_targets(scene, colour, rig=cal.rig)
    for target, image in zip(targets, colour):
        assert target.image.shape[0] == scene.camera.channels == 1
        np.testing.assert_allclose(target.image[0].numpy(), rgb2gray(image.permute(1, 2, 0).numpy()), atol=1e-6)
    assert torch.equal(targets[0].image, target_image("astronaut", 1))  # the file's, to the bit
    grey = target_image("camera", 1)
    assert torch.equal(image_with_channels(grey, 3), grey.expand(3, -1, -1))
    assert image_with_channels(grey, 1) is grey
    for bad, says in (((grey, 2), "channels must be 1 .grey. or 3"), ((None, 3), "image must be")):
        with pytest.raises(InputError, match=says):
            image_with_channels(*bad)
