"""`make demo`'s editable install prints no setuptools warning (issue 39 #13).

Before, setuptools installed the top-level packages through a meta path finder and warned on
every install ("BuildBackendWarning: Editable installation ... Please be careful with folders
in your working directory with the same name as your package"); `package-dir = {"" = "."}` in
pyproject.toml makes it a plain .pth entry for the repository. The editable wheel is built here
by the installed setuptools from a copy of the tracked sources.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_the_editable_install_builds_without_a_warning(tmp_path) -> None:
    src = tmp_path / "src"
    files = subprocess.run(
        ["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.split()
    for name in files:
        wanted = name.endswith((".py", ".toml", ".md")) or name.startswith("policy/weights/")
        if wanted and (ROOT / name).is_file():
            (src / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, src / name)
    out = tmp_path / "wheel"
    out.mkdir()
    run = subprocess.run(
        [
            sys.executable,
            "-W",
            "always",
            "-c",
            f"from setuptools import build_meta; print(build_meta.build_editable({str(out)!r}))",
        ],
        cwd=src,
        capture_output=True,
        text=True,
        timeout=120,
    )
    said = run.stdout + run.stderr
    assert run.returncode == 0, said[-2000:]
    assert "BuildBackendWarning" not in said and "Please be careful" not in said, said[-2000:]
    wheel = next(out.glob("*.whl"))
    names = zipfile.ZipFile(wheel).namelist()
    assert any(n.endswith(".pth") for n in names), names
