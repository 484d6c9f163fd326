"""Job configuration: defaults, TOML and validation."""
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from icefab import Job
from icefab.config import job_from_dict, load_job, to_toml
from icefab.errors import ConfigError


def test_defaults_are_the_cobra_600_cell():
    job = Job()
    assert job.slicing.layer_thickness_mm == 0.25
    assert job.materials.part.initial_offset_mm == 0.6
    assert job.materials.scaffold.initial_offset_mm == 1.2
    assert job.scaffold.buffer_mm == 3.3
    assert job.cell.l1_mm == 325.0 and job.cell.l2_mm == 275.0
    assert job.motion.joint_speed_deg_s == (33.0, 39.0)


def test_toml_round_trip(tmp_path):
    job = Job().replace(**{"slicing.layer_thickness_mm": 0.5, "materials.part.fill_pattern": "zigzag"})
    f = tmp_path / "job.toml"
    f.write_text(to_toml(job))
    back = load_job(f)
    assert back == job


@pytest.mark.parametrize("text, fragment", [
    ("[slicing]\nlayer_thickness_mm = -1\n", "job.toml:2: slicing.layer_thickness_mm = -1.0: must be >= 0.01 and <= 10"),
    ("[slicing]\nlayer_thicknes_mm = 1\n", "job.toml:2: unknown setting slicing.layer_thicknes_mm"),
    ("[parts]\n\ncopies = [0, 1, 1]\n", "job.toml:3: parts.copies = (0, 1, 1): must be >= 1"),
    ("[parts]\npart_fraction = [0, 1.5]\n", "job.toml:2: parts.part_fraction"),
    ("[slicing]\nmode = 3\n", "job.toml:2: slicing.mode = 3: expected a string"),
    ("[materials.part]\npath_width_mm = 0\n", "job.toml:2: materials.part.path_width_mm"),
    ("[nonsense]\nx = 1\n", "unknown setting nonsense"),
    ("[parts]\nrotation_order = [1, 1, 2]\n", "job.toml:2: parts.rotation_order = (1, 1, 2): "
     "must be a permutation"),
    ("[parts]\ncopies = [2, 1, 3]\n", "job.toml:2: parts.copies = (2, 1, 3): 3 copies do not "
     "fit a 2 x 1 grid"),
    ("slicing = { layer_thickness_mm = -1 }\n", "job.toml:1: slicing.layer_thickness_mm"),
    ("[flow]\nmode = \"pwm\"\npwm_frequency_hz = 2000\n", "job.toml:3: flow.pwm_frequency_hz = "
     "2000: must not exceed 1 / flow.tick_s = 500 Hz"),
    ("[flow]\n\ncalibration_pulse_ms = 0.2\n", "job.toml:3: flow.calibration_pulse_ms = 0.2"),
    ("[materials]\npart = { fill_width_mm = 3.0, path_width_mm = 0 }\n",
     "job.toml:2: materials.part.path_width_mm"),
    # hunt P: these three ended in Python's tracebacks (OverflowError, ValueError,
    # RecursionError)
    ("[slicing]\nlayer_thickness_mm = 1" + "0" * 400 + "\n",
     "job.toml:2: slicing.layer_thickness_mm: an integer of 401 digits"),
    ("[cell]\ncpus = 1" + "0" * 5000 + "\n", "job.toml: not valid TOML: Exceeds the limit"),
    ("x = " + "[" * 50000 + "]" * 50000 + "\n", "job.toml: not valid TOML: arrays or tables "
     "nested too deeply"),
    # a group left out was never laid, and its area was called filled (hunt P)
    ("[materials]\norder = [\"scaffold:fill\", \"part:boundary\"]\n",
     "job.toml:2: materials.order = ('scaffold:fill', 'part:boundary'): must list each of"),
    ("[materials]\norder = []\n", "job.toml:2: materials.order = (): must list each of"),
    ("[parts]\nfiles = [\"a.stl\", \"\"]\n", "job.toml:2: parts.files[1] = '': an empty file "
     "name"),
])
def test_bad_settings_name_setting_and_line(tmp_path, text, fragment):
    f = tmp_path / "job.toml"
    f.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_job(f)
    assert fragment in str(err.value)


def test_the_pwm_frequency_binds_only_pwm(tmp_path):
    # FM at max_frequency_hz = 100 was refused for PWM's 125 Hz, a setting FM never reads;
    # switching that job to PWM is refused with the reason
    fm = Job().replace(**{"flow.max_frequency_hz": 100.0})
    with pytest.raises(ConfigError, match="flow.pwm_frequency_hz = 125: must not exceed "
                                          "flow.max_frequency_hz = 100 Hz"):
        fm.replace(**{"flow.mode": "pwm"})


def test_python_construction_is_validated_too():
    with pytest.raises(ConfigError, match="scaffold.buffer_mm"):
        job_from_dict({"scaffold": {"buffer_mm": -2}})


def test_a_section_given_keeps_the_defaults_of_its_place(tmp_path):
    # a job file that sets one scaffold material setting keeps the scaffold's own defaults
    # (its initial offset, nozzle offset and density are not the part's): before, the
    # whole section was rebuilt from the generic material defaults
    f = tmp_path / "job.toml"
    f.write_text("[materials.scaffold]\npath_width_mm = 2.0\n[materials.part]\n"
                 "gap_fill = false\n")
    job, default = load_job(f), Job()
    assert job.materials.scaffold == default.materials.scaffold.__class__(
        **{**default.materials.scaffold.__dict__, "path_width_mm": 2.0})
    assert job.materials.scaffold.initial_offset_mm == 1.2
    assert job.materials.scaffold.nozzle_offset_mm == (0.2, 8.2)
    assert job.materials.part.gap_fill is False
    assert job_from_dict({"materials": {"scaffold": {"density_g_cm3": 0.9}}}
                         ).materials.scaffold.initial_offset_mm == 1.2
    with pytest.raises(ConfigError, match="materials.scaffold.initial_offset_mm"):
        job_from_dict({"materials": {"scaffold": {"initial_offset_mm": -1.0}}})


def test_relative_file_names_are_beside_the_job_file(tmp_path, monkeypatch):
    # a tester's relative calibration_file was read from the current folder, at every
    # later step (the job travels in the result files): the same trajectories gave other
    # valve programs depending on where 'icefab valves' ran
    (tmp_path / "job").mkdir()
    (tmp_path / "job" / "cal.csv").write_text("frequency_hz,flow_mm3_s\n0,0\n500,150\n")
    (tmp_path / "job" / "job.toml").write_text(
        '[parts]\nfiles = ["cube.obj"]\n[materials.part]\ncalibration_file = "cal.csv"\n'
        '[materials.scaffold]\ncalibration_file = "../other.csv"\n')
    monkeypatch.chdir(tmp_path)
    job = load_job("job/job.toml")
    assert job.parts.files == (str(tmp_path / "job" / "cube.obj"),)
    assert job.materials.part.calibration_file == str(tmp_path / "job" / "cal.csv")
    assert job.materials.scaffold.calibration_file == str(tmp_path / "other.csv")
    # stored so: a result file's job reads the same table from anywhere
    assert load_job_text(to_toml(job)).materials.part.calibration_file == str(
        tmp_path / "job" / "cal.csv")
    # the built-in table stays the built-in table
    (tmp_path / "plain.toml").write_text("[slicing]\nlayer_thickness_mm = 0.5\n")
    assert load_job("plain.toml").materials.part.calibration_file == ""


def load_job_text(text):
    import tomllib
    return job_from_dict(tomllib.loads(text))


def test_numpy_scalars_are_numbers():
    # a program's np.float32(0.5) was 'expected a number', np.int64(2) 'expected an integer'
    import numpy as np

    job = Job().replace(**{"slicing.layer_thickness_mm": np.float32(0.5),
                           "cell.cpus": np.int64(2)})
    assert job.slicing.layer_thickness_mm == 0.5 and type(job.cell.cpus) is int
    with pytest.raises(ConfigError, match="expected an integer"):
        Job().replace(**{"cell.cpus": np.float64(2.5)})
    with pytest.raises(ConfigError, match="must be >= 0.01"):
        Job().replace(**{"slicing.layer_thickness_mm": np.float64(-1.0)})


def test_a_job_built_directly_is_checked_as_a_file_is():
    # Job(motion=replace(..., speed_mm_s=np.float32(1e9))) skipped the range check (the
    # check let any non-Python number through); a string or a list went in as it was
    import dataclasses

    import numpy as np

    motion = Job().motion
    with pytest.raises(ConfigError, match=r"motion.speed_mm_s = 1000000000.0: must be"):
        Job(motion=dataclasses.replace(motion, speed_mm_s=np.float32(1e9)))
    with pytest.raises(ConfigError, match="motion.speed_mm_s = '100': expected a number"):
        Job(motion=dataclasses.replace(motion, speed_mm_s="100"))
    with pytest.raises(ConfigError, match="motion = .*expected a MotionSettings section"):
        Job(motion={"speed_mm_s": 100.0})
    job = Job(motion=dataclasses.replace(motion, speed_mm_s=np.float32(100)),
              cell=dataclasses.replace(Job().cell, ee_origin_mm=[300, np.int64(10)]))
    assert type(job.motion.speed_mm_s) is float and job.motion.speed_mm_s == 100.0
    assert job.cell.ee_origin_mm == (300.0, 10.0) and type(job.cell.ee_origin_mm) is tuple
    assert job == Job().replace(**{"motion.speed_mm_s": 100.0, "cell.ee_origin_mm": [300, 10]})


@settings(max_examples=200, deadline=None)
@given(st.text())
def test_toml_string_reads_back_whatever_the_text(text):
    """Any text (control characters, quotes, backslashes, characters beyond U+FFFF) as a
    TOML string reads back as itself: JSON's escapes of an emoji are surrogate pairs,
    which TOML refuses (a calibration's fragment for a folder named with one did not
    load)."""
    import tomllib

    from icefab.config import toml_string

    assert tomllib.loads(f"k = {toml_string(text)}")["k"] == text


def test_an_acceleration_whose_steps_cut_curves_past_the_bead_is_refused():
    """A trajectory sample every dt cuts a curve taken at the acceleration bound A by up
    to A dt^2 / 8: at 1e6 mm/s^2 and 16 ms, 32 mm (a hunt's 3 mm ring was two samples at
    one point, a 200 mm circle an octagon 17 mm off). Over half the narrowest path width
    it is refused, naming both settings; a finer step takes it."""
    with pytest.raises(ConfigError, match=r"motion.accel_mm_s2 = 1e\+06 with motion.dt_s = "
                       r"0.016: .* up to accel x dt\^2 / 8 = 32 mm .* \(1.5 mm\)"):
        Job().replace(**{"motion.accel_mm_s2": 1e6})
    assert Job().replace(**{"motion.accel_mm_s2": 1e6, "motion.dt_s": 0.002})
    assert Job().replace(**{"motion.accel_mm_s2": 5000.0})        # 0.16 mm
    with pytest.raises(ConfigError, match=r"\(0.25 mm\)"):
        Job().replace(**{"motion.accel_mm_s2": 5000.0, "materials.scaffold.path_width_mm": 0.25,
                         "materials.scaffold.fill_width_mm": 0.5})
