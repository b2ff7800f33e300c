"""Lint as part of the tests, as ROS packages do with ament_flake8 and ament_pep257."""

import pathlib
import shutil
import subprocess

ROOT = pathlib.Path(__file__).resolve().parent.parent


def test_ruff_finds_nothing():
    ruff = shutil.which('ruff')
    assert ruff, 'ruff is not installed (make venv installs it)'
    result = subprocess.run([ruff, 'check', '--no-cache', str(ROOT)], capture_output=True,
                            text=True, cwd=ROOT)
    assert result.returncode == 0, result.stdout + result.stderr
