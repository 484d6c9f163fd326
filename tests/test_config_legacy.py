"""The thesis' legacy control-parameter file (paper Table 1, thesis Table 3-1)."""
from pathlib import Path

import pytest

from icefab.config import load_job
from icefab.errors import ConfigError

# Paper Table 1 layout: values, [units], [format], description (restrictions).
PAPER_TABLE_1 = """\
1	[int] Number of STL and/or PLY files to import (> 0)
jamesmcgill.stl	[char char] STL and/or PLY file names (no spaces within each name)
0	[1/0 (on/off)] inexact option: used to indicate if common vertices for adjacent triangular facets are not identical
2	[1/2/3] Slicing option: 1, boundary paths are found; 2, boundary and fill paths are formed; 3, 2D option
1	[1/0 (on/off)] scaffolding option
1e-4	[float] Tolerance value for comparing floating-point data (>0)
1.5 1.5 [mm]	[float float] [part support] Deposition path width (> 0)
0.4 [mm]	[float] Slice thickness (> 0)
45 [deg]	[float] Max. angle between path segments that is considered to be smooth (> 0)
0 0 0 0	[1/0 float float float] [(on/off) Sx Sy Sz] Scaling vector (> 0)
1 -90 0 0 [deg]	[1/0 float float float] [(on/off) Rx Ry Rz] Rotation vector (1-2-3 Euler angles)
0 0 0 0 [mm]	[(1/0) Tx Ty Tz] [(on/off) Tx Ty Tz] Translation vector
0 1	[float float] [min max] Part fraction to slice: [0 1] indicates the entire part
0 1	[float float] [min max] Scaffolding subset
1 1 1	[int int int] [p1 p2 p3] Part copy vector: p3 part copies will be built, laid out in a grid
5 [mm]	[float] Scaffolding buffer
"""

# Thesis Table 3-1 layout: section headings in capitals, reference frames at the end.
THESIS_TABLE_3_1 = """\
CAD PARTS
2	[int] (>0) Number of STL and/or PLY files to import
body.stl handle.ply	[char char] STL and/or PLY file names; no spaces are allowed within each name
COMPUTATION
4	number of CPUs to use in parallel computations
SLICING CONTROL
1.5 1.2 [mm]	[float float] (> 0) [part scaffolding] deposition path width
0.25 [mm]	[float] (> 0) slice thickness
30 [deg]	[float] (> 0) maximum angle between adjacent path segments that is considered to be smooth
3.3 [mm]	[float] Scaffolding buffer
PART TRANSFORMATION
1 2 2 2	[1/0 float float float] (> 0) [(on/off) Sx Sy Sz] Scaling vector
1 -85 0 0 [deg]	[1/0 float float float] [(on/off) Rx Ry Rz] Rotation vector
3 1 2	[int int int] (1-3) Rotation axis order
1 cent orig 5 [mm]	[1/0 float float float] [(on/off) Tx Ty Tz] Translation vector
REFERENCE FRAMES
260 -100 [mm]	[float float] [EEx EEy] origin of the end effector (EE) frame in the Cobra 600 base frame
-0.1 -0.3 [mm]	[float float] [Wx Wy] origin of the water building frame in the EE frame
0.2 8.2 [mm]	[float float] [SCx SCy] origin of the scaffolding building frame in the EE frame
-30 19 [mm]	[float float] [Mx My] origin of the laser measurement frame in the EE frame
"""


def write(tmp_path: Path, text: str) -> Path:
    f = tmp_path / "control.txt"
    f.write_text(text)
    return f


def test_paper_table_1(tmp_path):
    job = load_job(write(tmp_path, PAPER_TABLE_1))
    assert [Path(f).name for f in job.parts.files] == ["jamesmcgill.stl"]
    assert job.slicing.layer_thickness_mm == 0.4
    assert job.motion.smooth_angle_deg == 45
    assert job.parts.rotation_deg == (-90.0, 0.0, 0.0)
    assert job.parts.scale == (1.0, 1.0, 1.0)            # switched off
    assert job.parts.translation == ("orig", "orig", "orig")  # switched off: keep
    assert job.scaffold.buffer_mm == 5.0
    assert job.scaffold.enabled is True
    assert job.parts.weld_tolerance_mm == 1e-4


def test_thesis_table_3_1(tmp_path):
    job = load_job(write(tmp_path, THESIS_TABLE_3_1))
    assert [Path(f).name for f in job.parts.files] == ["body.stl", "handle.ply"]
    assert job.cell.cpus == 4
    assert job.materials.part.path_width_mm == 1.5
    assert job.materials.scaffold.path_width_mm == 1.2
    assert job.parts.scale == (2.0, 2.0, 2.0)
    assert job.parts.rotation_order == (3, 1, 2)
    assert job.parts.translation == ("cent", "orig", 5.0)
    assert job.cell.ee_origin_mm == (260.0, -100.0)
    assert job.materials.scaffold.nozzle_offset_mm == (0.2, 8.2)
    assert job.cell.laser_offset_mm == (-30.0, 19.0)


@pytest.mark.parametrize("old, new, fragment", [
    ("0.25 [mm]	[float] (> 0) slice thickness", "-0.25 [mm]	[float] (> 0) slice thickness",
     "control.txt:8: slicing.layer_thickness_mm = -0.25: must be >= 0.01"),
    ("1.5 1.2 [mm]	[float float] (> 0) [part scaffolding] deposition path width",
     "1.5 0 [mm]	[float float] (> 0) [part scaffolding] deposition path width",
     "control.txt:7: materials.scaffold.path_width_mm = 0.0: must be >= 0.2"),
    ("0.25 [mm]	[float] (> 0) slice thickness", "abc [mm]	[float] (> 0) slice thickness",
     "control.txt:8: slice thickness: expected 1 number, got none"),
    ("3 1 2	[int int int]", "3 3 2	[int int int]", "control.txt:14: rotation axis order"),
    ("4	number of CPUs", "4	number of bananas", "control.txt:5: unrecognised control entry"),
    ("1 cent orig 5 [mm]", "1 middle orig 5 [mm]", "control.txt:15: translation"),
    ("1 cent orig 5 [mm]", "1 cent xyz 5 [mm]", "control.txt:15: translation vector: "
     "expected 4 entries (1/0, then Tx Ty Tz: each a number, cent or orig), got 1 cent "
     "before 'xyz'"),
    # a tester's "smoothing tolerance" set the weld tolerance (substring "tolerance")
    ("30 [deg]	[float] (> 0) maximum angle", "0.02 [mm] smoothing tolerance\n30 [deg]	"
     "[float] (> 0) maximum angle", "control.txt:9: control entry '0.02 [mm] smoothing "
     "tolerance' names several settings: 'tolerance', 'smooth'"),
    # the last of two won, unsaid
    ("3.3 [mm]	[float] Scaffolding buffer", "3.3 [mm]	[float] Scaffolding buffer\n"
     "2 [mm]	Scaffolding buffer", "control.txt:11: 'Scaffolding buffer' is given twice "
     "(line 10 too)"),
    # more names than the count, or names before it
    ("2	[int] (>0) Number", "1	[int] (>0) Number", "control.txt:3: 2 mesh file name(s) "
     "where the number of files leaves 1"),
    ("2	[int] (>0) Number of STL and/or PLY files to import\n", "",
     "control.txt:2: mesh file names before the number of files"),
])
def test_bad_legacy_entries_name_the_line(tmp_path, old, new, fragment):
    assert old in THESIS_TABLE_3_1
    with pytest.raises(ConfigError) as err:
        load_job(write(tmp_path, THESIS_TABLE_3_1.replace(old, new)))
    assert fragment in str(err.value)


def test_a_byte_order_mark_is_not_part_of_the_text(tmp_path):
    # Windows editors write one: the first entry read as "expected 1 number, got none",
    # and a TOML job as an invalid statement
    f = tmp_path / "control.txt"
    f.write_bytes(b"\xef\xbb\xbf" + PAPER_TABLE_1.encode())
    assert load_job(f).slicing.layer_thickness_mm == 0.4
    t = tmp_path / "job.toml"
    t.write_bytes(b"\xef\xbb\xbf[slicing]\nlayer_thickness_mm = 0.3\n")
    assert load_job(t).slicing.layer_thickness_mm == 0.3


def test_missing_file_names(tmp_path):
    text = "3	[int] Number of STL and/or PLY files to import\na.stl b.stl	[char] file names\n"
    with pytest.raises(ConfigError, match="1 mesh file name"):
        load_job(write(tmp_path, text))


def test_copy_vector_must_be_positive(tmp_path):
    text = PAPER_TABLE_1.replace("1 1 1	[int int int]", "2 0 1	[int int int]")
    with pytest.raises(ConfigError, match=r"control.txt:15: parts.copies"):
        load_job(write(tmp_path, text))


def test_part_fraction_error_names_its_line(tmp_path):
    text = PAPER_TABLE_1.replace("0 1	[float float] [min max] Part fraction",
                                 "0.5 1.5	[float float] [min max] Part fraction")
    with pytest.raises(ConfigError, match=r"control.txt:13: parts.part_fraction"):
        load_job(write(tmp_path, text))


# issue 10: inf/nan/1e400 in integer entries were an OverflowError traceback; 'nan inexact'
# was silently true. Every entry kind, every non-finite or non-whole spelling.
@pytest.mark.parametrize("bad", ["inf", "-inf", "nan", "NaN", "1e400", "-1e400", "2.5",
                                 "1e30"])
@pytest.mark.parametrize("old, template", [
    ("1	[int] Number of STL", "{} [int] Number of STL"),
    ("0	[1/0 (on/off)] inexact option", "{} [1/0 (on/off)] inexact option"),
    ("2	[1/2/3] Slicing option", "{} [1/2/3] Slicing option"),
    ("1	[1/0 (on/off)] scaffolding option", "{} [1/0 (on/off)] scaffolding option"),
    ("1 1 1	[int int int] [p1 p2 p3]", "1 {} 1	[int int int] [p1 p2 p3]"),
    ("0 0 0 0	[1/0 float float float] [(on/off) Sx", "{} 1 1 1	[1/0 float float float] "
                                                       "[(on/off) Sx"),
    ("1 -90 0 0 [deg]", "{} -90 0 0 [deg]"),
    ("0 0 0 0 [mm]	[(1/0) Tx", "{} 0 0 0 [mm]	[(1/0) Tx"),
    ("0.4 [mm]	[float] Slice thickness", "{} [mm]	[float] Slice thickness"),
    ("5 [mm]	[float] Scaffolding buffer", "{} [mm]	[float] Scaffolding buffer"),
])
def test_non_finite_or_fractional_entries_are_one_config_error(tmp_path, bad, old, template):
    assert old in PAPER_TABLE_1
    text = PAPER_TABLE_1.replace(old, template.format(bad))
    line = next(n for n, t in enumerate(text.splitlines(), 1) if t.startswith(bad) or
                f" {bad}" in t.split("[")[0])
    try:
        job = load_job(write(tmp_path, text))
    except ConfigError as err:
        assert f"control.txt:{line}:" in str(err) and "\n" not in str(err)
    else:
        # only a fraction where a length belongs may pass; never in a switch or a count
        assert bad == "2.5" and ("Slice thickness" in template or "buffer" in template)
        assert job is not None


def test_switches_accept_only_one_and_zero(tmp_path):
    on = load_job(write(tmp_path, PAPER_TABLE_1.replace(
        "0	[1/0 (on/off)] inexact option", "1	[1/0 (on/off)] inexact option")))
    assert on.parts.inexact is True
    with pytest.raises(ConfigError, match=r"control.txt:3: inexact option = 2: must be 1 "):
        load_job(write(tmp_path, PAPER_TABLE_1.replace(
            "0	[1/0 (on/off)] inexact option", "2	[1/0 (on/off)] inexact option")))


def test_a_toml_job_under_another_name_says_so(tmp_path):
    """A TOML job named 'fl.json' was read as a legacy control file and refused as
    "unrecognised control entry '[flow]'" (a reviewer's)."""
    f = tmp_path / "fl.json"
    f.write_text('[flow]\nout_of_range = "clamp"\n')
    with pytest.raises(ConfigError, match=r"fl.json:1: '\[flow\]' is a TOML table: a job "
                                          r"in TOML must be named '.toml'"):
        load_job(f)
