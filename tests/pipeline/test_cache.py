"""The calibration cache: read back whole, keyed by everything a calibration depends on, never trusted when broken."""

import dataclasses
import json
import os
import threading

import pytest
import torch
import yaml

from torchproj.cli import main
from torchproj.pipeline import run_virtual
from torchproj.pipeline.run import run_markdown
from torchproj.pipeline import scene_targets
from torchproj.pipeline.cache import (CACHE_DIR_ENV, CACHE_MAX_ENV, cached_calibration, cached_transport, calibration_key,
                                      geometry_key, keep_geometry, keep_normal_matrices, read_geometry, read_normal_matrices,
                                      transport_key, writing_behind)
from torchproj.core.errors import InputError
from torchproj.scene.show import shown_scene
from torchproj.sim import VirtualRig
from torchproj.transport import TransportOperator, build_transport
from torchproj.scene import parse_scene

from ..helpers import small_config


def _scene(**camera):
    return parse_scene(small_config(camera=(200, 150), projector=(128, 96), **camera), name="small")


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv(CACHE_DIR_ENV, str(tmp_path / "cache"))
    return tmp_path / "cache"


def test_a_second_run_reads_the_calibration_and_captures_the_same(cache):
    scene = _scene()
    first = run_virtual(scene, cache=True, progress=False).report
    second = run_virtual(scene, cache=True, progress=False).report
    plain = run_virtual(scene, progress=False).report
    assert (first["calibration_cache"], second["calibration_cache"], plain["calibration_cache"]) == ("stored", "read", "off")
    assert (first["transport_cache"], second["transport_cache"], plain["transport_cache"]) == ("stored", "read", "off")
    assert (first["cast_cache"], second["cast_cache"], plain["cast_cache"]) == ("stored", "read", "off")
    # The time the run waited for its writes is a stage of a run that wrote, and only of one.
    assert "keep" in first["timings_s"] and "keep" not in second["timings_s"] and "keep" not in plain["timings_s"]
    # report.md says where the calibration, the model and the rays the captures render from came from.
    text, plain_text = run_markdown(second), run_markdown(plain)
    assert "virtual rig (read from the cache)" in text and "nonzeros (read from the cache)" in text
    assert "cast through the scene (read from the cache)" in text
    assert "cache" not in plain_text.split("How each score")[0]
    # Another objective on a grey scene builds the same operator, and reads it.
    assert run_virtual(scene, cache=True, progress=False, objective="ssim").report["transport_cache"] == "read"
    # The rig's noise continues where calibration left it: the same captures, to the last bit.
    for a, b, c in zip(first["targets"], second["targets"], plain["targets"]):
        assert a["psnr_db"] == b["psnr_db"] == c["psnr_db"] and a["ssim"] == b["ssim"]
    assert len(list(cache.glob("*.pt"))) == 4  # the calibration, its transport and Q, the cast rays


def test_the_normal_matrix_a_solve_built_is_read_back_with_its_transport(cache):
    scene = _scene()
    # Without the smoothness penalty the solve runs on the operator kept, so its solver setup is kept too
    # (a smoothed solve's Q and levels add the penalty to these: tests/transport/test_operator.py).
    first = run_virtual(scene, cache=True, progress=False, smoothness=0)
    (entry,) = cache.glob("normal-*.pt")
    key = entry.name[len("normal-"):-3]
    (built,) = cached_transport(key, lambda: pytest.fail("built again instead of read"))[0]
    assert built.normal_matrix() is None
    # The coarse levels the first solve started from come back with Q.
    (levels,) = read_normal_matrices(key, [built])
    assert levels == len(first.solution.info["coarse_iterations"]) > 0
    # So do the Jacobi scaling FISTA ran each level on and that system's Lipschitz bound.
    scalings = [setup["jacobi"] for setup in built.solver_setup()]
    assert len(scalings) == levels + 1 and all(j is not None and j["lipschitz"] is not None for j in scalings)
    Q = built.normal_matrix()
    x = torch.rand(built.shape[1], 1, dtype=built.val.dtype)
    torch.testing.assert_close(Q @ x, built.A_adjoint(built.A(x)), rtol=1e-4, atol=1e-6)
    (fresh,) = cached_transport(key, lambda: pytest.fail("built again instead of read"))[0]
    read_back = built.coarse_matrices()
    for (ne, _), kept in zip(fresh.coarse_levels(levels), read_back, strict=True):  # P^T Q P built here
        torch.testing.assert_close(kept.to_dense(), ne.Q.to_dense())
    assert built.coarse_levels(levels)[0][0].Q is read_back[0]  # used, not built again
    for ne, j in zip(fresh._normal_levels(), scalings, strict=True):  # computed here: the same, bit for bit
        assert torch.equal(ne.jacobi().Q.values(), j["values"]) and torch.equal(ne.jacobi().scale, j["scale"])
        assert ne.jacobi().lipschitz() == j["lipschitz"]
    with pytest.raises(InputError, match="kept lipschitz must be a positive number"):
        built.adopt_solver_setup([{"lipschitz": -1.0, "jacobi": None}])
    with pytest.raises(InputError, match="kept Jacobi scaling"):
        built.adopt_solver_setup([{"lipschitz": None, "jacobi": dict(scalings[0], scale=scalings[0]["scale"][:-1])}])
    # The next run solves on it and lands where the first did.
    again = run_virtual(scene, cache=True, progress=False, solver="pgd")
    assert again.report["transport_cache"] == "read"
    plain = run_virtual(scene, progress=False, solver="pgd")
    assert again.solution.objective == plain.solution.objective
    assert first.report["transport_cache"] == "stored"
    # A Q of another shape is refused; an unreadable entry is dropped and Q built again by the solver.
    with pytest.raises(InputError, match="Q must be a CSR matrix"):
        built.adopt_normal_matrix(torch.eye(3, dtype=Q.dtype).to_sparse_csr())
    with pytest.raises(InputError, match="coarse level's matrix must be a CSR matrix"):
        built.adopt_coarse_matrices([torch.eye(3, dtype=Q.dtype).to_sparse_csr()])
    entry.write_bytes(entry.read_bytes()[:700])
    with pytest.warns(UserWarning, match="normal matrix cache entry .* is unreadable"):
        assert read_normal_matrices(key, [built]) is None
    assert not entry.exists()


def test_coarse_levels_a_later_solve_builds_are_kept_beside_a_q_read(cache):
    """LF builds Q and no coarse level; FISTA after it reads Q, builds the levels and keeps them too."""
    scene = _scene()
    assert run_virtual(scene, cache=True, progress=False, solver="lf").report["transport_cache"] == "stored"
    (entry,) = cache.glob("normal-*.pt")
    key = entry.name[len("normal-"):-3]

    def levels_kept():
        (op,) = cached_transport(key, lambda: pytest.fail("built again instead of read"))[0]
        return read_normal_matrices(key, [op])

    assert levels_kept() == [0]
    fista = run_virtual(scene, cache=True, progress=False, smoothness=0)
    assert levels_kept() == [len(fista.solution.info["coarse_iterations"])] != [0]


def test_a_smoothed_solve_keeps_its_own_normal_equations_and_a_later_one_reads_them(cache, monkeypatch):
    """The default solve runs on the operator with the smoothness rows: its Q, coarse levels and setup are
    kept under their own key, and the next run solves from them without building Q, to the same patterns."""
    import torchproj.transport.operator as operator_module
    from torchproj.core.choices import DEFAULT_SMOOTHNESS
    from torchproj.pipeline.cache import smoothed_key

    scene = _scene()
    first = run_virtual(scene, cache=True, progress=False)
    assert first.report["smoothness"] == DEFAULT_SMOOTHNESS
    (transport,) = [p.name[len("transport-"):-3] for p in cache.glob("transport-*.pt")]
    (entry,) = cache.glob("normal-*.pt")
    assert entry.name == f"normal-{smoothed_key(transport, DEFAULT_SMOOTHNESS)}.pt"
    monkeypatch.setattr(operator_module, "gram_matrix", lambda *a, **k: pytest.fail("Q built again instead of read"))
    again = run_virtual(scene, cache=True, progress=False)
    monkeypatch.undo()
    plain = run_virtual(scene, progress=False)
    assert again.solution.objective == first.solution.objective == plain.solution.objective
    assert [t.psnr_db for t in again.targets] == [t.psnr_db for t in plain.targets]


def test_a_normal_entry_whose_coarse_level_does_not_fit_is_not_half_adopted(cache, monkeypatch):
    scene = _scene()
    run_virtual(scene, cache=True, progress=False, smoothness=0)  # the entry of the transport's own Q
    (entry,) = cache.glob("normal-*.pt")
    key = entry.name[len("normal-"):-3]
    (op,) = cached_transport(key, lambda: pytest.fail("built again instead of read"))[0]
    assert read_normal_matrices(key, [op]) is not None
    # The same Q, with a coarse level of another size: refused whole, Q included, and the entry removed.
    monkeypatch.setattr(TransportOperator, "coarse_matrices", lambda self: [torch.eye(3).to_sparse_csr()])
    assert keep_normal_matrices(key, [op])
    (again,) = cached_transport(key, lambda: pytest.fail("built again instead of read"))[0]
    with pytest.warns(UserWarning, match="normal matrix cache entry .* is unreadable"):
        assert read_normal_matrices(key, [again]) is None
    assert again.normal_matrix() is None and not entry.exists()


def test_the_cast_rays_read_back_render_what_casting_renders(cache):
    scene = _scene()
    rig = VirtualRig(scene)
    assert read_geometry(rig) is None  # nothing kept yet: the rig casts
    rig.geometry("near")
    assert keep_geometry(rig) == "stored"
    again = VirtualRig(dataclasses.replace(scene, name="renamed"))  # the name is not the world
    assert read_geometry(again) == "read" and list(again.cast_geometry()) == ["near"]
    patterns = {j: torch.rand(2, 1, p.height, p.width) for j, p in enumerate(scene.projectors)}
    assert torch.equal(again.radiance("near", patterns), VirtualRig(scene).radiance("near", patterns))
    assert torch.equal(again.surface_mask("near"), rig.surface_mask("near"))
    # Another world has another key; a rig of another camera refuses the rays, and the entry is dropped.
    other = _scene(exposure=1.7)
    assert geometry_key(other) != geometry_key(scene)
    wider = parse_scene(small_config(camera=(240, 150), projector=(128, 96)), name="small")
    (entry,) = cache.glob("geometry-*.pt")
    payload = torch.load(entry, weights_only=False)
    torch.save(dict(payload, key=geometry_key(wider)), cache / f"geometry-{geometry_key(wider)}.pt")
    entry.unlink()
    with pytest.warns(UserWarning, match="cast geometry cache entry .* is unreadable .*does not fit projector"):
        assert read_geometry(VirtualRig(wider)) is None
    assert not list(cache.glob("geometry-*.pt"))
    # A truncated entry is not trusted either.
    keep_geometry(rig)
    (entry,) = cache.glob("geometry-*.pt")
    entry.write_bytes(entry.read_bytes()[:800])
    fresh = VirtualRig(scene)
    with pytest.warns(UserWarning, match="is unreadable"):
        assert read_geometry(fresh) is None
    assert not fresh.cast_geometry()


def test_a_changed_world_keeps_and_reads_its_own_rays(cache):
    """With ``show:``, the captures are the changed world's: its rays are kept and read, not the calibrated ones."""
    data = small_config(camera=(200, 150), projector=(128, 96))
    scene = parse_scene(dict(data, show={"projectors": {"upper": {"translation_mm": [2, 0, 0]}}}), name="bumped")
    first = run_virtual(scene, cache=True, progress=False).report
    second = run_virtual(scene, cache=True, progress=False).report
    assert (first["cast_cache"], second["cast_cache"]) == ("stored", "read")
    assert [t["psnr_db"] for t in first["targets"]] == [t["psnr_db"] for t in second["targets"]]
    keys = {p.name.split("-", 1)[1][:-3] for p in cache.glob("geometry-*.pt")}
    assert keys == {geometry_key(shown_scene(scene))}


def test_the_transport_read_back_is_the_one_built_and_its_key_follows_targets_and_options(cache):
    scene = _scene()
    cal, _ = cached_calibration(scene)
    targets = scene_targets(scene, None, cal.rig)
    base = calibration_key(scene, oracle=False, bits=None, plane_tolerance=1.0)
    options = dict(footprint="area", merge=False, colour_weights="grey", device="cpu")
    key = transport_key(base, targets, **options)
    built, how = cached_transport(key, lambda: [build_transport(cal.states, targets, merge=False)])
    assert how == "stored"
    (read,), how = cached_transport(key, lambda: pytest.fail("built again instead of read"))
    assert how == "read"
    for name, tensor in built[0].named_buffers():
        assert torch.equal(tensor, dict(read.named_buffers())[name]), name
    assert read.get_extra_state() == built[0].get_extra_state()
    x = torch.rand(read.shape[1], read.channels, dtype=read.rhs.dtype)
    assert torch.equal(read.A(x), built[0].A(x)) and torch.equal(read.A_adjoint(read.rhs), built[0].A_adjoint(read.rhs))
    # Another image, another footprint, another calibration: another key.
    brighter = [dataclasses.replace(targets[0], image=targets[0].image * 0.5), *targets[1:]]
    assert transport_key(base, brighter, **options) != key
    assert transport_key(base, targets, **dict(options, footprint="nearest")) != key
    assert transport_key(base + "x", targets, **options) != key
    # A broken entry is rebuilt, not trusted.
    (entry,) = cache.glob("transport-*.pt")
    entry.write_bytes(entry.read_bytes()[:500])
    with pytest.warns(UserWarning, match="transport cache entry .* is unreadable"):
        _, how = cached_transport(key, lambda: [build_transport(cal.states, targets, merge=False)])
    assert how == "recomputed"


def test_a_transport_entry_is_mapped_and_one_kept_without_its_transpose_still_reads(cache):
    """Entries are mapped, not read (POSIX): an operator read back works on after its entry is removed
    (evicted by a later run). An entry kept before transposes were (no ``transpose``) is read, and its
    transpose computed."""
    scene = _scene()
    cal, _ = cached_calibration(scene)
    targets = scene_targets(scene, None, cal.rig)
    key = transport_key(calibration_key(scene, oracle=False, bits=None, plane_tolerance=1.0), targets,
                        footprint="area", merge=False, colour_weights="grey", device="cpu")
    (built,), _ = cached_transport(key, lambda: [build_transport(cal.states, targets, merge=False)])
    (entry,) = cache.glob("transport-*.pt")
    payload = torch.load(entry, weights_only=False)
    del payload["operators"][0]["transpose"]
    torch.save(payload, entry)
    (read,), how = cached_transport(key, lambda: pytest.fail("built again instead of read"))
    assert how == "read"
    entry.unlink()
    x = torch.rand(read.shape[1], read.channels, dtype=read.rhs.dtype)
    y = torch.rand(read.shape[0], read.channels, dtype=read.rhs.dtype)
    assert torch.equal(read.A(x), built.A(x)) and torch.equal(read.A_adjoint(y), built.A_adjoint(y))
    for name in ("t_crow", "t_col", "t_val"):
        assert torch.equal(getattr(read, name), getattr(built, name)), name


def test_reading_an_entry_says_nothing_of_sparse_invariant_checks(cache, monkeypatch):
    """torch.load (2.11 with CUDA) warned on every run from the cache that CSR support is beta and that
    sparse invariant checks are implicitly off; they are off as for every CSR torchproj builds, and a
    user is not told each time."""
    import warnings

    scene = _scene()
    cal, _ = cached_calibration(scene)
    targets = scene_targets(scene, None, cal.rig)
    key = transport_key(calibration_key(scene, oracle=False, bits=None, plane_tolerance=1.0), targets,
                        footprint="area", merge=False, colour_weights="grey", device="cpu")
    cached_transport(key, lambda: [build_transport(cal.states, targets, merge=False)])
    load = torch.load

    def load_as_cuda_torch_does(*args, **kwargs):
        warnings.warn("Sparse CSR tensor support is in beta state. If you miss a functionality in the sparse "
                      "tensor support, please submit a feature request", UserWarning, stacklevel=2)
        warnings.warn("Sparse invariant checks are implicitly disabled. Memory errors (e.g. SEGFAULT) will occur "
                      "when operating on a sparse tensor which violates the invariants", UserWarning, stacklevel=2)
        return load(*args, **kwargs)

    monkeypatch.setattr(torch, "load", load_as_cuda_torch_does)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        (read,), how = cached_transport(key, lambda: pytest.fail("built again instead of read"))
    assert how == "read" and read.shape[0] > 0
    assert not [w for w in seen if "Sparse" in str(w.message)]


def test_the_key_follows_the_scene_and_options_not_its_name_targets_or_show():
    scene = _scene()
    key = calibration_key(scene, oracle=False, bits=None, plane_tolerance=1.0)
    data = small_config(camera=(200, 150), projector=(128, 96))
    renamed = parse_scene(dict(data, show={"ambient": 0.05}), name="other")
    assert calibration_key(renamed, oracle=False, bits=None, plane_tolerance=1.0) == key
    assert calibration_key(_scene(exposure=1.7), oracle=False, bits=None, plane_tolerance=1.0) != key
    assert calibration_key(scene, oracle=False, bits=3, plane_tolerance=1.0) != key


def test_a_broken_entry_is_recomputed_and_the_cache_keeps_to_its_size(cache, monkeypatch):
    scene = _scene()
    cal, how = cached_calibration(scene)
    assert how == "stored"
    (entry,) = cache.glob("*.pt")
    entry.write_bytes(entry.read_bytes()[:1000])  # truncated: a full disk, a killed writer
    with pytest.warns(UserWarning, match="is unreadable"):
        again, how = cached_calibration(scene)
    assert how == "recomputed"
    torch.testing.assert_close(again.black["near"], cal.black["near"])
    # Past the cap the least recently used go first, never the entry just written.
    monkeypatch.setenv(CACHE_MAX_ENV, "1e-9")
    cached_calibration(_scene(exposure=1.7))
    assert len(list(cache.glob("*.pt"))) == 1


def test_entries_another_process_removes_cost_a_computation_not_a_warning(cache, monkeypatch, recwarn):
    """Runs that share a cache folder (a sweep run side by side, the test suite's workers) each keep it to
    the cap, so an entry may go between being found, read and marked used: one read whole stands, one
    gone before it was read is computed again. Neither is a broken entry to warn about."""
    import torchproj.pipeline.cache as cache_module

    scene = _scene()
    cal, _ = cached_calibration(scene)
    (entry,) = cache.glob("*.pt")
    touch = cache_module.os.utime

    def removed_after_reading(path, *args, **kwargs):
        entry.unlink()
        return touch(path, *args, **kwargs)

    with monkeypatch.context() as patch:
        patch.setattr(cache_module.os, "utime", removed_after_reading)
        read, how = cached_calibration(scene)
    assert how == "read" and not entry.exists()
    torch.testing.assert_close(read.black["near"], cal.black["near"])
    cached_calibration(scene)  # kept again
    load = torch.load

    def removed_before_reading(path, *args, **kwargs):
        entry.unlink()
        return load(path, *args, **kwargs)

    with monkeypatch.context() as patch:
        patch.setattr(torch, "load", removed_before_reading)
        again, how = cached_calibration(scene)
    torch.testing.assert_close(again.black["near"], cal.black["near"])
    assert entry.exists() and not [w for w in recwarn if "cache" in str(w.message)]


def test_the_cap_counts_the_entries_still_there(tmp_path, monkeypatch):
    from pathlib import Path

    from torchproj.pipeline.cache import _evict

    folder = tmp_path / "cache"
    folder.mkdir()
    for age, name in enumerate(("old", "new", "kept")):
        (folder / f"{name}.pt").write_bytes(bytes(1000))
        os.utime(folder / f"{name}.pt", (age, age))
    # Listed, then removed by another run keeping its own cap before its size was read.
    listing = Path.glob
    monkeypatch.setenv(CACHE_MAX_ENV, str(2500 / 1e9))
    with monkeypatch.context() as patch:
        patch.setattr(Path, "glob", lambda self, pattern: [folder / "gone.pt", *listing(self, pattern)])
        _evict(folder, keep=folder / "kept.pt")
    assert sorted(p.name for p in folder.glob("*.pt")) == ["kept.pt", "new.pt"]


def test_a_cache_folder_that_refuses_the_entries_is_reported_not_kept(tmp_path, monkeypatch):
    """A cache path that is a file (or a full disk): the run goes on, warns, and says nothing was kept."""
    blocked = tmp_path / "a_file"
    blocked.write_text("not a folder")
    monkeypatch.setenv(CACHE_DIR_ENV, str(blocked))
    with pytest.warns(UserWarning, match="could not keep the calibration"):
        report = run_virtual(_scene(), cache=True, progress=False).report
    assert (report["calibration_cache"], report["transport_cache"], report["cast_cache"]) == ("not kept",) * 3
    assert "(computed: the cache folder refused to keep it)" in run_markdown(report)


def test_no_cache_from_the_command_line(cache, tmp_path):
    config = tmp_path / "small.yaml"
    config.write_text(yaml.safe_dump(dict(small_config(camera=(200, 150), projector=(128, 96)), name="small")))
    assert main(["run", str(config), "--no-cache", "--out", str(tmp_path / "a")]) == 0
    report = json.loads((tmp_path / "a" / "report.json").read_text())
    assert (report["calibration_cache"], report["transport_cache"]) == ("off", "off")
    assert not cache.exists()
    assert main(["run", str(config), "--out", str(tmp_path / "b")]) == 0
    assert json.loads((tmp_path / "b" / "report.json").read_text())["calibration_cache"] == "stored"


def test_entries_written_behind_are_whole_when_the_block_ends_and_hold_what_was_kept(cache):
    """Within writing_behind the entries are written on another thread; leaving the block waits for them,
    and each holds the payload as it was kept, whatever the caller changed in its own containers after."""
    from torchproj.pipeline.cache import _write

    writers = []
    real_save = torch.save

    def save(payload, path):
        writers.append(threading.current_thread())
        real_save(payload, path)

    states = {"near": torch.arange(4.0)}
    payload = {"key": "k", "states": states}
    with pytest.MonkeyPatch.context() as m:
        m.setattr(torch, "save", save)
        with writing_behind() as behind:
            assert _write(cache, cache / "entry.pt", payload, "calibration")
            states["far"] = torch.zeros(2)  # the run goes on changing its own dict
        assert not behind.refused
    assert writers and all(t is not threading.main_thread() for t in writers)
    kept = torch.load(cache / "entry.pt", weights_only=False)
    assert list(kept["states"]) == ["near"] and torch.equal(kept["states"]["near"], torch.arange(4.0))
    assert not list(cache.glob(".partial-*"))


def test_a_write_refused_behind_the_run_is_reported_not_kept(cache, monkeypatch):
    """A disk that refuses an entry while the run goes on (full, say): the run finishes, warns once it has
    waited for its writes, and its report says which entry was not kept; nothing half-written stays."""
    real_save = torch.save

    def save(payload, path):
        if "operators" in payload:
            raise RuntimeError("No space left on device")
        real_save(payload, path)

    monkeypatch.setattr(torch, "save", save)
    with pytest.warns(UserWarning, match="could not keep the transport"):
        report = run_virtual(_scene(), cache=True, progress=False).report
    assert (report["calibration_cache"], report["transport_cache"], report["cast_cache"]) == ("stored", "not kept", "stored")
    assert not list(cache.glob("transport-*")) and not list(cache.glob(".partial-*"))
    monkeypatch.setattr(torch, "save", real_save)
    again = run_virtual(_scene(), cache=True, progress=False).report
    assert (again["calibration_cache"], again["transport_cache"], again["cast_cache"]) == ("read", "stored", "read")


def test_a_block_that_raises_finishes_the_entry_being_written_and_drops_the_rest(cache):
    """Ctrl-C during a run: the entry on the writer is finished whole, those not begun are not written,
    and no partial file is left; the interrupt goes on up."""
    from torchproj.pipeline.cache import _write

    started, release = threading.Event(), threading.Event()
    real_save = torch.save

    def slow_save(payload, path):
        started.set()
        release.wait(5)
        real_save(payload, path)

    with pytest.MonkeyPatch.context() as m:
        m.setattr(torch, "save", slow_save)
        with pytest.raises(KeyboardInterrupt):
            with writing_behind():
                _write(cache, cache / "first.pt", {"key": "first"}, "calibration")
                _write(cache, cache / "second.pt", {"key": "second"}, "transport")
                assert started.wait(5)
                # The first write goes on a second after the interrupt, long after the block has
                # dropped the second (at once, on leaving).
                threading.Timer(1.0, release.set).start()
                raise KeyboardInterrupt
    assert sorted(p.name for p in cache.iterdir()) == ["first.pt"]
    assert torch.load(cache / "first.pt", weights_only=False) == {"key": "first"}


def test_a_block_writes_behind_for_its_own_thread_only(cache):
    """A run in another thread while one writes behind: the other thread's entry is written as it would be
    alone, not queued behind this block's."""
    from torchproj.pipeline.cache import _write

    release = threading.Event()
    real_save = torch.save

    def save(payload, path):
        if payload["key"] == "mine":
            release.wait(5)
        real_save(payload, path)

    seen = {}

    def other_run():
        seen["kept"] = _write(cache, cache / "theirs.pt", {"key": "theirs"}, "calibration")
        seen["whole"] = (cache / "theirs.pt").is_file()

    with pytest.MonkeyPatch.context() as m:
        m.setattr(torch, "save", save)
        with writing_behind():
            assert _write(cache, cache / "mine.pt", {"key": "mine"}, "calibration")
            other = threading.Thread(target=other_run)
            other.start()
            other.join(5)
            assert seen == {"kept": True, "whole": True} and not (cache / "mine.pt").exists()
            release.set()
    assert (cache / "mine.pt").is_file()
