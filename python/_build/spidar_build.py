"""The package's own PEP 517 build backend: writes the pure-Python wheel
with the standard library alone.

A fresh venv of Python 3.11 has pip and setuptools 65 but not `wheel`,
which setuptools before 70.1 needs to build any wheel, and an offline
machine cannot fetch it; this backend needs nothing, so `pip install
./python` works offline in a fresh venv (no build isolation needed, none
hurts). The wheel holds the `spidar` package and its metadata (wheel
format 1.0: METADATA, WHEEL, RECORD with sha256 of every file).
"""

import base64
import hashlib
import io
import os
import pathlib
import tarfile
import zipfile

NAME = "spidar"
VERSION = "0.1.0"
SUMMARY = "A SPIDAR haptic device from Python: ctypes over libspidar_capi (the C API in capi/)."
ROOT = pathlib.Path(__file__).resolve().parent.parent
TAG = "py3-none-any"


def _metadata():
    return (
        "Metadata-Version: 2.1\n"
        f"Name: {NAME}\n"
        f"Version: {VERSION}\n"
        f"Summary: {SUMMARY}\n"
        "License: MIT OR Apache-2.0\n"
        "Requires-Python: >=3.8\n"
    )


def _wheel_file():
    return (
        "Wheel-Version: 1.0\n"
        "Generator: spidar_build\n"
        "Root-Is-Purelib: true\n"
        f"Tag: {TAG}\n"
    )


def _record_line(path, data):
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return f"{path},sha256={digest},{len(data)}\n"


def _files():
    """(path in the wheel, bytes) of the package's modules."""
    pkg = ROOT / NAME
    for f in sorted(pkg.rglob("*.py")):
        yield f.relative_to(ROOT).as_posix(), f.read_bytes()


def get_requires_for_build_wheel(config_settings=None):
    return []


def get_requires_for_build_sdist(config_settings=None):
    return []


def prepare_metadata_for_build_wheel(metadata_directory, config_settings=None):
    dist_info = f"{NAME}-{VERSION}.dist-info"
    d = pathlib.Path(metadata_directory) / dist_info
    d.mkdir(parents=True, exist_ok=True)
    (d / "METADATA").write_text(_metadata())
    (d / "WHEEL").write_text(_wheel_file())
    return dist_info


def build_wheel(wheel_directory, config_settings=None, metadata_directory=None):
    name = f"{NAME}-{VERSION}-{TAG}.whl"
    dist_info = f"{NAME}-{VERSION}.dist-info"
    entries = list(_files())
    entries.append((f"{dist_info}/METADATA", _metadata().encode()))
    entries.append((f"{dist_info}/WHEEL", _wheel_file().encode()))
    record = "".join(_record_line(p, data) for p, data in entries)
    record += f"{dist_info}/RECORD,,\n"
    path = os.path.join(wheel_directory, name)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for p, data in entries:
            z.writestr(p, data)
        z.writestr(f"{dist_info}/RECORD", record)
    return name


def build_sdist(sdist_directory, config_settings=None):
    base = f"{NAME}-{VERSION}"
    name = f"{base}.tar.gz"
    with tarfile.open(os.path.join(sdist_directory, name), "w:gz") as t:
        for rel in ["pyproject.toml", "_build/spidar_build.py"]:
            t.add(ROOT / rel, arcname=f"{base}/{rel}")
        for p, _ in _files():
            t.add(ROOT / p, arcname=f"{base}/{p}")
        data = _metadata().encode()
        info = tarfile.TarInfo(f"{base}/PKG-INFO")
        info.size = len(data)
        t.addfile(info, io.BytesIO(data))
    return name
