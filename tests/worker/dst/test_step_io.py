import pytest

from worker.dst.errors import EmptyGeometryError, NotASolidError, StepReadError
from worker.dst.step_io import read_step, sniff_step, solid_volume


def test_sniff_accepts_part21_and_refuses_others():
    assert sniff_step(b"ISO-10303-21;\nHEADER;")
    assert sniff_step(b"\xef\xbb\xbf  iso-10303-21;")
    assert not sniff_step(b"solid stl")
    assert not sniff_step(b"")


def test_inch_file_is_read_in_millimetres(make_step):
    path = make_step("cone", radius=1.0, height=2.0, nurbs=False, unit="INCH")
    part = read_step(path)
    assert any("INCH" in w.upper() for w in part.warnings)
    # build123d built it in mm; the writer declared inches and scaled, the reader scales back
    assert solid_volume(part.solids[0]) == pytest.approx(3.14159265 * 1.0 * 2.0 / 3.0, rel=1e-6)


def test_open_shell_is_not_a_solid(tmp_path):
    import build123d as bd

    from tests.conftest import write_step

    face = bd.Face.make_rect(10, 10)
    path = write_step(face, tmp_path / "face.step", nurbs=False)
    with pytest.raises(NotASolidError):
        read_step(path)


def test_truncated_file_is_a_read_error(make_step, tmp_path):
    good = make_step("cone", radius=2, height=2).read_bytes()
    bad = tmp_path / "cut.step"
    bad.write_bytes(good[: len(good) // 2])
    with pytest.raises((StepReadError, EmptyGeometryError, NotASolidError)):
        read_step(bad)
