"""What setup.py declares, read by running it with setuptools.setup replaced (shared by the
package and launch-file tests; pytest puts this folder on sys.path)."""

from __future__ import annotations

import os
import runpy
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def setup_kwargs() -> dict:
    """The keyword arguments setup.py passes to setuptools.setup."""
    import setuptools

    captured: dict = {}
    original_setup, original_cwd = setuptools.setup, os.getcwd()
    setuptools.setup = lambda **kwargs: captured.update(kwargs)
    try:
        runpy.run_path(str(REPO / "setup.py"), run_name="__main__")
    finally:
        setuptools.setup = original_setup
        os.chdir(original_cwd)
    return captured


def console_scripts() -> dict[str, str]:
    """Console script name -> its "module:function" target."""
    scripts = {}
    for spec in setup_kwargs()["entry_points"]["console_scripts"]:
        name, target = (part.strip() for part in spec.split("=", 1))
        scripts[name] = target
    return scripts
