"""Building a task's model prints no MuJoCo deprecation note and writes no MUJOCO_LOG.TXT into
the current directory, and the model is the one MuJoCo compiles from dm_control's XML."""
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np

from tasks.dm_control.common import load_suite_model, suite_model_files

ROOT = Path(__file__).resolve().parents[2]


def test_building_cheetah_is_quiet_and_leaves_no_log_file(tmp_path):
    code = ("from tasks.dm_control.common import load_suite_model; "
            "load_suite_model('cheetah'); print('built')")
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                          text=True, timeout=120, env={"PYTHONPATH": str(ROOT),
                                                       "PATH": "/usr/bin:/bin"})
    assert done.returncode == 0 and done.stdout == "built\n", done.stderr
    assert "settotalmass" not in done.stdout + done.stderr, done.stderr
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()


def test_the_quiet_model_is_dm_controls_bit_for_bit(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # MuJoCo's own handler writes its log file here
    xml, assets = suite_model_files("cheetah")
    plain, quiet = mujoco.MjModel.from_xml_string(xml, assets), load_suite_model("cheetah")
    for name in dir(plain):
        value = getattr(plain, name)
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(getattr(quiet, name), value, err_msg=name)
    assert (quiet.stat.meanmass, quiet.stat.meaninertia) == (plain.stat.meanmass,
                                                              plain.stat.meaninertia)
    assert quiet.body_mass.sum() == plain.body_mass.sum()
