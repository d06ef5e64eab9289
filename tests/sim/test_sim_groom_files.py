"""Strands files (DESIGN section 3) are validated before anything large is read: every
problem is one line naming the file and the dataset, exit status 2 from the main job,
no traceback (2 ranks: tests/io/test_mpi_job.py)."""

from pathlib import Path

import h5py
import numpy as np
import pytest

from lc_petsc.batch import main
from lc_petsc.scene import geometry
from lc_petsc.scene.sources import FileSource

N = 30            # vertices per wisp, two wisps


def _good(path, **override):
    """A valid two-wisp strands file, with datasets replaced or added by ``override``
    (a value None removes the dataset)."""
    pos = np.concatenate([geometry.wisp4c(N, root=(2.0 * w, 0.0, 0.0)) for w in range(2)])
    data = {"positions": pos, "wisp_offsets": np.array([0, N, 2 * N], np.int64),
            "radius": np.full(2 * N, 0.05), "pinned": np.tile(np.arange(N) < 3, 2)}
    data.update(override)
    with h5py.File(path, "w") as f:
        for k, v in data.items():
            if v is not None:
                f[k] = v
    return str(path)


CASES = {
    "short radius": (dict(radius=np.full(2 * N - 1, 0.05)), "/radius must have one entry per vertex"),
    "long radius": (dict(radius=np.full(2 * N + 5, 0.05)), "/radius must have one entry per vertex"),
    "short pinned": (dict(pinned=np.zeros(5, bool)), "/pinned must have one entry per vertex"),
    "complex positions": ("complex", "/positions has type complex128, expected real floating-point"),
    "string positions": ("bytes", "/positions has type |S"),
    "float offsets": (dict(wisp_offsets=np.array([0.0, N, 2 * N])), "/wisp_offsets has type float64"),
    "float pinned": (dict(pinned=np.zeros(2 * N)), "/pinned has type float64, expected booleans"),
    "pinned 2": (dict(pinned=np.full(2 * N, 2, np.int8)), "/pinned holds values other than 0 and 1"),
    "negative radius": (dict(radius=np.full(2 * N, -1.0)), "/radius must be finite and positive; vertex 0 has -1.0"),
    "nan radius at 7": (dict(radius=np.where(np.arange(2 * N) == 7, np.nan, 0.05)),
                        "/radius must be finite and positive; vertex 7 has nan"),
    "nan positions": ("nan", "/positions must be finite; vertex 33 (wisp 1, its vertex 3) has [0.0, nan, inf]"),
    "bad offsets": (dict(wisp_offsets=np.array([0, N, 2 * N + 1])), "/wisp_offsets must start at 0"),
    "missing offsets": (dict(wisp_offsets=None), "missing dataset /wisp_offsets"),
    "2-D radius": (dict(radius=np.full((2 * N, 1), 0.05)), "/radius must have one entry per vertex"),
}


def _make(tmp_path, case):
    change, _ = CASES[case]
    p = tmp_path / "g.h5"
    if case == "complex positions":
        pos = np.concatenate([geometry.wisp4c(N), geometry.wisp4c(N)]).astype(complex)
        return _good(p, positions=pos)
    if case == "string positions":
        return _good(p, positions=np.full((2 * N, 3), b"1.0"))
    if case == "nan positions":
        pos = np.concatenate([geometry.wisp4c(N), geometry.wisp4c(N)])
        pos[N + 3] = (0.0, np.nan, np.inf)
        return _good(p, positions=pos)
    return _good(p, **change)


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_dataset_named(tmp_path, case):
    path = _make(tmp_path, case)
    with pytest.raises(ValueError) as e:
        FileSource(path)
    msg = str(e.value)
    assert CASES[case][1] in msg and path in msg and "\n" not in msg, msg


def _links(tmp_path, kind):
    p = tmp_path / f"{kind}.h5"
    _good(p, positions=None)
    with h5py.File(p, "a") as f:
        if kind == "soft":
            f["elsewhere"] = np.zeros((2 * N, 3))
            f["positions"] = h5py.SoftLink("/elsewhere")
        elif kind == "dangling":
            f["positions"] = h5py.SoftLink("/nothing")
        elif kind == "external":
            f["positions"] = h5py.ExternalLink("other.h5", "/positions")
        elif kind == "group":
            f.create_group("positions")
        elif kind == "external_storage":
            victim = tmp_path / "host_file.bin"
            victim.write_bytes(np.zeros(2 * N * 3).tobytes())
            f.create_dataset("positions", shape=(2 * N, 3), dtype="f8",
                             external=[(str(victim), 0, h5py.h5f.UNLIMITED)])
    return str(p)


@pytest.mark.parametrize("kind,needle", [("soft", "/positions is a soft link"),
                                         ("dangling", "/positions is a soft link"),
                                         ("external", "/positions is an external link"),
                                         ("group", "/positions is a group, not a dataset"),
                                         ("external_storage", "/positions keeps its data in other files")])
def test_links_groups_and_external_storage_refused(tmp_path, kind, needle):
    with pytest.raises(ValueError, match=needle):
        FileSource(_links(tmp_path, kind))


def test_not_hdf5_empty_truncated(tmp_path):
    empty = tmp_path / "empty.h5"
    empty.write_bytes(b"")
    with pytest.raises(ValueError, match="is empty .0 bytes."):
        FileSource(str(empty))
    text = tmp_path / "text.h5"
    text.write_text("positions = 1\n")
    with pytest.raises(ValueError, match="not an HDF5 file"):
        FileSource(str(text))
    good = Path(_good(tmp_path / "good.h5"))
    cut = tmp_path / "cut.h5"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(ValueError, match="truncated"):
        FileSource(str(cut))


def test_huge_declared_vertex_count_refused_before_reading(tmp_path):
    """An 800 kB file declaring 1e9 vertices (chunked, nothing stored) is refused by the
    memory estimate; main ran the machine out of memory on it."""
    p = tmp_path / "huge.h5"
    with h5py.File(p, "w") as f:
        f.create_dataset("positions", shape=(10 ** 9, 3), dtype="f8", chunks=(4096, 3))
        f["wisp_offsets"] = np.array([0, 10 ** 9], np.int64)
    assert p.stat().st_size < 1_000_000
    with pytest.raises(ValueError, match=r"/positions declares 1,000,000,000 vertices; .* GB of memory"):
        FileSource(str(p))


def test_memory_check_counts_every_node_of_the_job(tmp_path, monkeypatch):
    """The memory estimate is held against the memory of all the job's nodes, not one:
    a groom needing 3 machines' worth is refused on one node and on two, and passes the
    memory check on four (8 ranks, 2 per node); the node count comes from the launcher."""
    from lc_petsc.scene import sources
    assert sources.job_nodes({"OMPI_COMM_WORLD_SIZE": "8", "OMPI_COMM_WORLD_LOCAL_SIZE": "2"}) == 4
    assert sources.job_nodes({"OMPI_COMM_WORLD_SIZE": "3", "OMPI_COMM_WORLD_LOCAL_SIZE": "2"}) == 2
    assert sources.job_nodes({"SLURM_JOB_NUM_NODES": "16"}) == 16
    assert sources.job_nodes({}) == 1
    # a machine of 1 MiB: 768 vertices need 3 MiB at 4 kiB per vertex
    monkeypatch.setattr(sources, "machine_memory", lambda: 1 << 20)
    path = _good(tmp_path / "g.h5")
    with h5py.File(path) as f:
        nv = f["positions"].shape[0]
    monkeypatch.setattr(sources, "BYTES_PER_VERTEX", 3 * (1 << 20) // nv)
    for nodes, refused in ((1, True), (2, True), (4, False)):
        monkeypatch.setattr(sources, "job_nodes", lambda n=nodes: n)
        if refused:
            where = "this machine has" if nodes == 1 else f"this job's {nodes} nodes have"
            with pytest.raises(ValueError, match=f"{where} .* GB of memory; run on more nodes"):
                sources.FileSource(str(path))
        else:
            assert sources.FileSource(str(path)).n_wisps > 0


def test_main_job_reports_once_with_exit_2(tmp_path, capsys):
    path = _make(tmp_path, "short radius")
    cfg = tmp_path / "f.toml"
    cfg.write_text(f'[scene]\nkind = "file"\npath = "{path}"\n[output]\npreviews = false\n')
    assert main([str(cfg), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("error:") == 1 and "/radius must have one entry per vertex" in err
    assert "Traceback" not in err and not (tmp_path / "o").exists()
    # the shipped example still loads
    assert FileSource(str(Path(__file__).resolve().parents[2] / "configs" / "data" / "fringe.h5")).n_wisps == 24


def _toml(tmp_path, path, kind="file", extra=""):
    cfg = tmp_path / "g.toml"
    cfg.write_text(f'[scene]\nkind = "{kind}"\npath = "{path}"\n{extra}[output]\npreviews = false\n'
                   'usd = false\n')
    return str(cfg)


def _run_err(capsys, cfg, out):
    capsys.readouterr()
    assert main([cfg, "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("error:") == 1 and "Traceback" not in err
    return err


def test_rest_state_errors_name_the_groom_file(tmp_path, capsys):
    """A problem LocalScene.build finds in a groom (not the file check) names the file:
    duplicate vertices, a wisp of 3 vertices, and (ccd) wisps that touch at rest."""
    pos = np.concatenate([geometry.wisp4c(N, root=(2.0 * w, 0.0, 0.0)) for w in range(2)])
    pos[N + 6] = pos[N + 5]                              # wisp 1, edge 5: zero length
    dup = _good(tmp_path / "dup.h5", positions=pos)
    err = _run_err(capsys, _toml(tmp_path, dup), tmp_path / "o")
    assert f"error: strands file {dup}: wisp 1, edge 5: rest length 0.0 is zero (coincident " \
           "vertices); remove the duplicate vertex from the groom" in err
    short = _good(tmp_path / "short.h5", positions=pos[:N + 3], wisp_offsets=np.array([0, N, N + 3]),
                  radius=None, pinned=None)
    err = _run_err(capsys, _toml(tmp_path, short), tmp_path / "o")
    assert f"error: strands file {short}: wisp 1 has 3 vertices; a wisp needs at least 4" in err
    close = np.concatenate([geometry.wisp4c(N, root=(0.05 * w, 0.0, 0.0)) for w in range(2)])
    touch = _good(tmp_path / "touch.h5", positions=close)
    ccd = ('[physics]\nterms = ["stretch", "bend", "twist", "strand_collision"]\n'
           'strand_contact_mode = "ccd"\n[time]\ninitial_guess = "follow_the_leader"\n')
    err = _run_err(capsys, _toml(tmp_path, touch, extra=ccd), tmp_path / "o")
    assert f"error: strands file {touch}: rest pose: " in err and "closer than the contact thickness" in err
    # the thickness was not set: the message says where it came from; set, it does not
    assert "(physics.strand_thickness is not set: twice the scene's smallest vertex radius)" in err
    err = _run_err(capsys, _toml(tmp_path, touch, extra=ccd.replace('"ccd"\n', '"ccd"\nstrand_thickness = 0.2\n')),
                   tmp_path / "o")
    assert "the contact thickness 0.2 cm; the closest" in err
    assert not (tmp_path / "o").exists()


def test_rest_state_errors_name_the_usd_file(tmp_path, capsys):
    from pxr import Usd, UsdGeom, Vt
    p = geometry.wisp4c(N)
    p[8] = p[7]
    stage = Usd.Stage.CreateNew(str(tmp_path / "dup.usda"))
    c = UsdGeom.BasisCurves.Define(stage, "/groom/curves")
    c.CreateTypeAttr("linear")
    c.CreateCurveVertexCountsAttr(Vt.IntArray([N]))
    c.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(p.astype(np.float32)))
    stage.GetRootLayer().Save()
    err = _run_err(capsys, _toml(tmp_path, tmp_path / "dup.usda", kind="usd"), tmp_path / "o")
    assert f"error: USD file {tmp_path / 'dup.usda'}: wisp 0, edge 7: rest length 0.0 is zero" in err


FRINGE = Path(__file__).resolve().parents[2] / "configs" / "data" / "fringe.h5"


def _flipped(tmp_path, vertex, axis, bit):
    """A copy of the shipped fringe with bit ``bit`` of one coordinate flipped (a damaged
    file: HDF5 has no checksum on a groom's datasets unless its writer asked for one)."""
    with h5py.File(FRINGE) as f:
        data = {k: f[k][...] for k in f}
    pos = data["positions"]
    word = pos[vertex:vertex + 1, axis].view(np.uint64)
    word ^= np.uint64(1) << np.uint64(bit)
    path = tmp_path / f"flip_{vertex}_{axis}_{bit}.h5"
    with h5py.File(path, "w") as f:
        for k, v in data.items():
            f[k] = v
    return path, data["wisp_offsets"]


def test_a_displaced_vertex_is_refused_naming_wisp_and_vertex(tmp_path, capsys):
    """One flipped exponent bit in fringe.h5 ran without an error (its crossings exempted
    as rest overlaps); a vertex far from both of its neighbours is now refused."""
    with h5py.File(FRINGE) as f:
        off = f["wisp_offsets"][...]
    v = int(off[5]) + 20                     # wisp 5, its vertex 20
    path, _ = _flipped(tmp_path, v, 1, 53)   # y (about -4 cm) x 4
    err = _run_err(capsys, _toml(tmp_path, path), tmp_path / "o")
    assert f"error: strands file {path}: wisp 5, vertex 20: it lies " in err, err
    assert "times the wisp's median edge" in err and "a displaced vertex (a damaged file" in err
    assert not (tmp_path / "o").exists()


def test_a_displaced_end_vertex_is_warned_about(tmp_path, capsys):
    """A wisp's last vertex has one neighbour: its long edge is a warning naming it."""
    with h5py.File(FRINGE) as f:
        off = f["wisp_offsets"][...]
    v = int(off[3]) - 1                      # wisp 2's tip
    path, _ = _flipped(tmp_path, v, 1, 53)
    cfg = _toml(tmp_path, path)
    capsys.readouterr()
    assert main([cfg, "--out", str(tmp_path / "o"), "--quiet", "--frames", "0"]) == 0
    err = capsys.readouterr().err
    n = int(off[3] - off[2])
    assert (f"{path}: 1 wisp(s) have an edge 5 or more times their wisp's median edge; the longest: "
            f"wisp 2, edge {n - 2} (vertices {n - 2}, {n - 1})") in err, err
