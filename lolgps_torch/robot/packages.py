"""Where a URDF's mesh files are, found the way ROS tools find them.

``package://PKG/rest`` names ``rest`` inside the folder of package ``PKG``.  That folder is
looked for, in order:

1. among the URDF's ancestor folders: one named ``PKG``, one holding a sub-folder ``PKG``, or
   one whose ``package.xml`` names ``PKG`` (a package's URDF usually sits inside it);
2. in each folder of the ``ROS_PACKAGE_PATH`` environment variable, then of the
   ``--package-path`` folders: the folder itself if it is ``PKG`` (by name or ``package.xml``),
   or a package ``PKG`` up to three levels below it (ROS searches these folders recursively);
3. last, ``rest`` beside the URDF or in its parent folder (descriptions copied without their
   package layout).

``file://`` URIs and absolute paths are taken as they are; relative paths are relative to the
URDF's folder (then its parent).  A name that is found nowhere resolves to None.
"""

from __future__ import annotations

import functools
import os
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Sequence

_PACKAGE = "package://"
_FILE = "file://"
_SEARCH_DEPTH = 3  # levels below a package-path folder searched for package.xml


def resolve_mesh(name: str, urdf_path: str, package_path: Sequence[str] = ()) -> str | None:
    """Absolute path of the file a URDF at ``urdf_path`` names ``name``, or None if not found.

    :param name: the ``filename`` attribute as written in the URDF.
    :param urdf_path: the URDF file (its folder and ancestors are searched).
    :param package_path: folders searched after ``ROS_PACKAGE_PATH`` (``--package-path``).
    """
    base = os.path.dirname(os.path.abspath(urdf_path))
    if name.startswith(_PACKAGE):
        package, _, rest = name[len(_PACKAGE) :].partition("/")
        folders = [*_ancestor_packages(package, base), *_listed_packages(package, package_path)]
        candidates = [os.path.join(folder, rest) for folder in folders]
        candidates += [os.path.join(folder, rest) for folder in (base, os.path.dirname(base))]
    elif name.startswith(_FILE):
        candidates = [name[len(_FILE) :]]
    elif "://" in name or not name:
        return None
    else:  # an absolute name ignores the folder it is joined to
        candidates = [os.path.join(folder, name) for folder in (base, os.path.dirname(base))]
    return next((os.path.abspath(c) for c in candidates if os.path.isfile(c)), None)


def _ancestor_packages(package: str, base: str) -> Iterator[str]:
    """Folders of ``package`` among ``base`` and its ancestors (step 1 of the module docstring)."""
    folder = base
    while True:
        if os.path.basename(folder) == package or _package_name(folder) == package:
            yield folder
        if os.path.isdir(os.path.join(folder, package)):
            yield os.path.join(folder, package)
        parent = os.path.dirname(folder)
        if parent == folder:
            return
        folder = parent


def _listed_packages(package: str, package_path: Sequence[str]) -> Iterator[str]:
    """Folders of ``package`` in ``ROS_PACKAGE_PATH`` and then ``package_path`` (step 2)."""
    listed = [p for p in os.environ.get("ROS_PACKAGE_PATH", "").split(os.pathsep) if p]
    for root in [*listed, *package_path]:
        yield from _packages_below(os.path.abspath(root), package, _SEARCH_DEPTH)


def _packages_below(folder: str, package: str, depth: int) -> Iterator[str]:
    if not os.path.isdir(folder):
        return
    if os.path.basename(folder) == package or _package_name(folder) == package:
        yield folder
        return
    if depth == 0:
        return
    try:
        entries = sorted(os.scandir(folder), key=lambda e: e.name)
    except OSError:
        return
    for entry in entries:
        if entry.is_dir() and not entry.name.startswith("."):
            yield from _packages_below(entry.path, package, depth - 1)


@functools.lru_cache(maxsize=256)
def _package_name(folder: str) -> str | None:
    """The ``<name>`` that ``folder/package.xml`` declares, or None."""
    manifest = os.path.join(folder, "package.xml")
    if not os.path.isfile(manifest):
        return None
    try:
        name = ET.parse(manifest).getroot().find("name")
    except (ET.ParseError, OSError):
        return None
    return name.text.strip() if name is not None and name.text else None
