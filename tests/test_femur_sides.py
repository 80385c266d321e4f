"""Left and right femurs: the side told from the head's offset from the shaft axis, on LLP26's
real (left) femurs and their mirror images, and a population that mirrors its right femurs into
the template's side and records it per subject."""
import os
import shutil

import numpy as np
import pytest

clgs_femur = pytest.importorskip("clgs_femur")


def _file_mesh(sid):
    with np.load(os.path.join(clgs_femur.DATA_DIR, f"femur_left_LLP26_subject{sid}.npz"), allow_pickle=False) as z:
        return np.asarray(z["vertices"], np.float64), np.asarray(z["faces"], np.int64)


def test_every_llp26_femur_is_left_and_its_mirror_image_right():
    from clgs.anatomy.sides import mirror_x

    for sid in clgs_femur.SUBJECTS:
        v, f = _file_mesh(sid)
        side, offset = clgs_femur.femur_side(v)
        assert side == "left" and offset < -10.0, (sid, side, offset)
        mv, mf = mirror_x(v, f)
        mside, moffset = clgs_femur.femur_side(mv)
        assert mside == "right" and moffset == pytest.approx(-offset, abs=1e-6)
        if sid == "00":  # mirrored in place, faces reversed: the same solid, outward normals
            import trimesh

            a, b = trimesh.Trimesh(v, f, process=False), trimesh.Trimesh(mv, mf, process=False)
            assert b.volume == pytest.approx(a.volume, rel=1e-9) and b.volume > 0
            np.testing.assert_allclose(mv.mean(0), v.mean(0), atol=1e-9)


def test_a_straight_rod_has_no_side():
    import trimesh

    rod = trimesh.creation.cylinder(radius=12.0, height=400.0, sections=32)
    assert clgs_femur.femur_side(rod.vertices)[0] == "undecided"


def test_decide_sides_mirrors_the_minority_into_the_majoritys_side():
    from clgs.anatomy.sides import decide_sides

    table = {"a": ("left", -20.0), "b": ("right", 21.0), "c": ("left", -19.0), "d": ("undecided", 1.0),
             "e": ("right", 22.0)}
    answers = iter(table.values())
    out = decide_sides({k: np.zeros((1, 3)) for k in table}, lambda v: next(answers),
                       ["a", "b", "c", "d"])
    assert out["template_side"] == "left"
    assert {k: r["mirrored"] for k, r in out["subjects"].items()} == {"a": False, "b": True, "c": False, "d": False,
                                                                        "e": True}
    assert out["subjects"]["d"]["side"] == "undecided"


def test_a_population_mirrors_a_right_femur_file_and_records_it(tmp_path, monkeypatch):
    from clgs.anatomy.population import SurfacePopulation
    from clgs.anatomy.sides import mirror_x
    from clgs.shape import builder

    ids = ["00", "01", "02", "03"]
    for sid in ids:
        shutil.copy(os.path.join(clgs_femur.DATA_DIR, f"femur_left_LLP26_subject{sid}.npz"), tmp_path)
    v, f = _file_mesh("02")
    mv, mf = mirror_x(v, f)
    np.savez(tmp_path / "femur_left_LLP26_subject02.npz", vertices=mv, faces=mf)  # a right femur

    def population(side_of):
        return SurfacePopulation.centred(shape=clgs_femur.SHAPE, spacing_mm=clgs_femur.SPACING_MM, pixel_mm=3.0,
                                         name="femur", summary="x", version="0", data_dir=tmp_path,
                                         file_pattern="femur_left_LLP26_subject{id}.npz", ids=ids, test_ids=["03"],
                                         params=clgs_femur.params(), frame_offset=clgs_femur.FRAME_OFFSET,
                                         side_of=side_of)

    pop = population(clgs_femur.femur_side)
    sides = pop.sides()
    assert sides["template_side"] == "left"
    assert [sid for sid, r in sides["subjects"].items() if r["mirrored"]] == ["02"]
    assert sides["subjects"]["02"]["side"] == "right" and sides["subjects"]["02"]["measure_mm"] > 10
    # the mesh the model and the simulator see is the left femur again
    got_v, got_f = pop.mesh("02")
    np.testing.assert_allclose(got_v, v - clgs_femur.FRAME_OFFSET, atol=1e-9)
    assert np.array_equal(got_f, f)
    assert pop.settings_hash() != population(None).settings_hash()  # mirroring is part of what a model depends on
    # the build records what was done, per model subject
    seen = {}
    monkeypatch.setattr(builder, "build_model", lambda *a, **k: seen.update(k))
    monkeypatch.setattr(pop, "load_template", lambda: None)
    monkeypatch.setattr(os.path, "getmtime", lambda p: 0.0)
    pop.build_model(out_path=str(tmp_path / "m.npz"))
    rec = seen["extra_meta"]["mirroring"]
    assert rec["template_side"] == "left" and set(rec["subjects"]) == {"00", "01", "02"}
    assert rec["subjects"]["02"]["mirrored"] and not rec["subjects"]["00"]["mirrored"] and rec["rule"]
