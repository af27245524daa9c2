"""The check the tests of the installed package make first: install/ must hold the tree's files."""

from __future__ import annotations

import shutil

from ros_helpers import stale_install


def _tree_with_install(root):
    """A package tree and a colcon-like install of it, the same files in both."""
    files = {"convbki_core/a.py": "A = 1\n", "convbki_ros/sub/b.py": "B = 2\n", "config/mapper.yaml": "x: 1\n",
             "launch/mapper.launch.py": "L = 3\n"}
    site = root / "install" / "convbki_ros" / "lib" / "python3.11" / "site-packages"
    share = root / "install" / "convbki_ros" / "share" / "convbki_ros"
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
        installed = (site if name.endswith(".py") and not name.startswith("launch") else share) / name
        installed.parent.mkdir(parents=True, exist_ok=True)
        installed.write_text(text)
    return site, share


def test_a_current_install_passes_and_an_edit_a_new_file_or_no_build_is_named(tmp_path):
    site, share = _tree_with_install(tmp_path)
    assert stale_install(tmp_path) is None
    (tmp_path / "convbki_ros" / "sub" / "b.py").write_text("B = 3\n")  # edited after the build
    assert stale_install(tmp_path) == "convbki_ros/sub/b.py"
    (site / "convbki_ros" / "sub" / "b.py").write_text("B = 3\n")
    (tmp_path / "config" / "new.yaml").write_text("y: 2\n")  # added after the build
    assert stale_install(tmp_path) == "config/new.yaml"
    (share / "config" / "new.yaml").write_text("y: 2\n")
    assert stale_install(tmp_path) is None
    shutil.rmtree(tmp_path / "install")
    assert stale_install(tmp_path) == "install/convbki_ros (not built)"
