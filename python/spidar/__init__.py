"""A SPIDAR haptic device from Python, over libspidar_capi (the C API, capi/).

ctypes, not a compiled extension: installing needs no compiler and no
network, and one build of libspidar_capi serves C, C++ and Python alike.

The library is found at $SPIDAR_LIBRARY (a path to libspidar_capi.so), else in
$CARGO_TARGET_DIR/{release,debug}, else in the repository's
target/{release,debug} when the package runs from a checkout, else on the
system's library path.

Units: mm, N, µs; positions and forces in the room frame of the device's
model. Errors raise SpidarError (its .code is the C code, its message names
the port and the cause); DisarmedError when the device disarmed itself
(its heartbeat watchdog after a stalled application).

    import spidar
    with spidar.Device.open_virtual(seed=1) as dev:
        dev.arm()
        s = dev.wait_state()
        dev.set_force(0.0, 0.0, 1.0)
"""

import ctypes
import ctypes.util
import json
import os
import pathlib
import subprocess
import tempfile

STRINGS = 8

_LIB_NAMES = ["libspidar_capi.so", "libspidar_capi.dylib", "spidar_capi.dll"]


class SpidarError(Exception):
    """A failed call: `code` is the C error code, `name` its name."""

    def __init__(self, code, name, message):
        super().__init__(f"{name}: {message}")
        self.code = code
        self.name = name
        self.message = message


class DisarmedError(SpidarError):
    """The device disarmed itself since arm() (its watchdog, a fault)."""


class _State(ctypes.Structure):
    _fields_ = [
        ("time_us", ctypes.c_uint64),
        ("since_home_us", ctypes.c_uint64),
        ("home_id", ctypes.c_uint64),
        ("index", ctypes.c_uint64),
        ("age_us", ctypes.c_uint64),
        ("lost", ctypes.c_uint64),
        ("position_mm", ctypes.c_double * 3),
        ("rendered_force_n", ctypes.c_double * 3),
        ("counts", ctypes.c_int32 * STRINGS),
        ("tensions_n", ctypes.c_float * STRINGS),
        ("faults", ctypes.c_uint16),
        ("armed", ctypes.c_uint8),
        ("motors_on", ctypes.c_uint8),
        ("slack", ctypes.c_uint8),
        ("excluded", ctypes.c_int8),
        ("has_model", ctypes.c_uint8),
        ("model_id", ctypes.c_uint32),
        ("fault_names", ctypes.c_char * 128),
    ]


class _Info(ctypes.Structure):
    _fields_ = [
        ("protocol_version", ctypes.c_uint16),
        ("firmware_version", ctypes.c_uint16 * 3),
        ("device_id", ctypes.c_char * 25),
        ("capabilities", ctypes.c_uint32),
        ("max_blob_len", ctypes.c_uint32),
        ("loop_period_us", ctypes.c_uint32),
        ("strings", ctypes.c_uint32),
    ]


class _ModelInfo(ctypes.Structure):
    _fields_ = [
        ("has_model", ctypes.c_uint8),
        ("slot", ctypes.c_uint8),
        ("correction", ctypes.c_uint8),
        ("strings", ctypes.c_uint8),
        ("model_id", ctypes.c_uint32),
        ("blob_crc32", ctypes.c_uint32),
        ("created_unix_s", ctypes.c_uint32),
        ("body_len", ctypes.c_uint32),
    ]


class _VirtualOptions(ctypes.Structure):
    _fields_ = [
        ("seed", ctypes.c_uint64),
        ("heartbeat_timeout_ms", ctypes.c_uint32),
        ("fast", ctypes.c_uint8),
        ("hold", ctypes.c_uint8),
    ]


class _LinkStats(ctypes.Structure):
    _fields_ = [
        ("states", ctypes.c_uint64),
        ("lost", ctypes.c_uint64),
        ("rejected", ctypes.c_uint64),
        ("device_dropped", ctypes.c_uint64),
        ("heartbeat_losses", ctypes.c_uint32),
        ("loop_overruns", ctypes.c_uint32),
    ]


_STRUCTS = {
    b"spidar_link_stats": _LinkStats,
    b"spidar_state": _State,
    b"spidar_info": _Info,
    b"spidar_model_info": _ModelInfo,
    b"spidar_virtual_options": _VirtualOptions,
}

_API_VERSION = 2
_DISARMED = -7


def _candidates():
    env = os.environ.get("SPIDAR_LIBRARY")
    if env:
        return [pathlib.Path(env)], True
    dirs = []
    target = os.environ.get("CARGO_TARGET_DIR")
    if target:
        dirs += [pathlib.Path(target) / "release", pathlib.Path(target) / "debug"]
    repo = pathlib.Path(__file__).resolve().parent.parent.parent
    if (repo / "capi" / "Cargo.toml").is_file():
        # Run from a checkout (python/spidar/): its cargo target dir.
        dirs += [repo / "target" / "release", repo / "target" / "debug"]
    return [d / n for d in dirs for n in _LIB_NAMES], False


def _load():
    paths, explicit = _candidates()
    for p in paths:
        if p.is_file():
            return ctypes.CDLL(str(p))
    if explicit:
        raise OSError(f"SPIDAR_LIBRARY={paths[0]}: no such file (build it with "
                      "`cargo build --release -p spidar-capi`)")
    found = ctypes.util.find_library("spidar_capi")
    if found:
        return ctypes.CDLL(found)
    looked = "\n  ".join(str(p) for p in paths)
    raise OSError("libspidar_capi not found: set SPIDAR_LIBRARY to the path of libspidar_capi.so "
                  "(`cargo build --release -p spidar-capi` makes it in target/release/), "
                  f"or CARGO_TARGET_DIR; looked at:\n  {looked}\nand the system's library path")


def _bind(lib):
    p = ctypes.POINTER
    dev = ctypes.c_void_p
    sigs = {
        "spidar_open": ([ctypes.c_char_p, p(dev)], ctypes.c_int32),
        "spidar_open_virtual": ([p(_VirtualOptions), p(dev)], ctypes.c_int32),
        "spidar_close": ([dev], ctypes.c_int32),
        "spidar_get_info": ([dev, p(_Info)], ctypes.c_int32),
        "spidar_arm": ([dev], ctypes.c_int32),
        "spidar_disarm": ([dev], ctypes.c_int32),
        "spidar_heartbeat": ([dev], ctypes.c_int32),
        "spidar_set_force": ([dev, ctypes.c_double, ctypes.c_double, ctypes.c_double],
                             ctypes.c_int32),
        "spidar_get_state": ([dev, p(_State)], ctypes.c_int32),
        "spidar_wait_state": ([dev, ctypes.c_uint32, p(_State)], ctypes.c_int32),
        "spidar_flash": ([dev, ctypes.c_char_p, ctypes.c_size_t, p(_ModelInfo)], ctypes.c_int32),
        "spidar_use_model": ([dev, ctypes.c_char_p, ctypes.c_size_t], ctypes.c_int32),
        "spidar_get_model_info": ([dev, p(_ModelInfo)], ctypes.c_int32),
        "spidar_get_link_stats": ([dev, p(_LinkStats)], ctypes.c_int32),
        "spidar_last_error": ([], ctypes.c_char_p),
        "spidar_error_name": ([ctypes.c_int32], ctypes.c_char_p),
        "spidar_api_version": ([], ctypes.c_uint32),
        "spidar_struct_size": ([ctypes.c_char_p], ctypes.c_size_t),
    }
    for name, (args, res) in sigs.items():
        f = getattr(lib, name)
        f.argtypes = args
        f.restype = res
    if lib.spidar_api_version() != _API_VERSION:
        raise OSError(f"libspidar_capi is API {lib.spidar_api_version()}, this package is "
                      f"API {_API_VERSION}: rebuild one of them from the same checkout")
    for name, cls in _STRUCTS.items():
        size = lib.spidar_struct_size(name)
        if size != ctypes.sizeof(cls):
            raise OSError(f"libspidar_capi's {name.decode()} is {size} bytes, this package's "
                          f"{ctypes.sizeof(cls)}: rebuild one of them from the same checkout")
    return lib


_lib = None


def library():
    """The loaded libspidar_capi (loaded and checked on first use)."""
    global _lib
    if _lib is None:
        _lib = _bind(_load())
    return _lib


def _check(rc):
    if rc != 0:
        lib = library()
        name = lib.spidar_error_name(rc).decode()
        message = lib.spidar_last_error().decode(errors="replace")
        cls = DisarmedError if rc == _DISARMED else SpidarError
        raise cls(rc, name, message)


def _state_dict(s):
    return {
        "time_us": s.time_us,
        "since_home_us": s.since_home_us,
        "home_id": s.home_id,
        "index": s.index,
        "age_us": s.age_us,
        "lost": s.lost,
        "position_mm": tuple(s.position_mm),
        "rendered_force_n": tuple(s.rendered_force_n),
        "counts": tuple(s.counts),
        "tensions_n": tuple(s.tensions_n),
        "faults": [n for n in s.fault_names.decode().split(",") if n],
        "fault_bits": s.faults,
        "armed": bool(s.armed),
        "motors_on": bool(s.motors_on),
        "slack": s.slack,
        "excluded": None if s.excluded < 0 else s.excluded,
        "model_id": s.model_id if s.has_model else None,
    }


def _model_dict(m):
    if not m.has_model:
        return None
    return {
        "model_id": m.model_id,
        "slot": m.slot,
        "correction": {0: "none", 1: "nn", 2: "svr"}.get(m.correction, str(m.correction)),
        "strings": m.strings,
        "blob_crc32": m.blob_crc32,
        "created_unix_s": m.created_unix_s,
        "body_len": m.body_len,
    }


class Device:
    """An open SPIDAR (CHAI3D's cGenericHapticDevice, dhd's device id).

    States are dicts: time_us, since_home_us, home_id, position_mm (room frame),
    rendered_force_n (room frame), counts, tensions_n, faults (names),
    armed, motors_on, age_us (host time since it arrived), lost, ...
    """

    def __init__(self, handle):
        self._h = handle

    @classmethod
    def open(cls, port):
        """Opens the device on a serial port ("/dev/ttyACM0")."""
        h = ctypes.c_void_p()
        _check(library().spidar_open(port.encode(), ctypes.byref(h)))
        return cls(h)

    @classmethod
    def open_virtual(cls, seed=0, heartbeat_timeout_ms=0, fast=False, hold=False):
        """Starts a virtual device in this process (its true calibration
        flashed) and opens it. heartbeat_timeout_ms 0: the firmware's."""
        opts = _VirtualOptions(seed, heartbeat_timeout_ms, int(fast), int(hold))
        h = ctypes.c_void_p()
        _check(library().spidar_open_virtual(ctypes.byref(opts), ctypes.byref(h)))
        return cls(h)

    def _handle(self):
        if self._h is None:
            raise SpidarError(-14, "SPIDAR_E_CLOSED", "the device is closed")
        return self._h

    def close(self):
        """No force, disarm, stream off, port closed (idempotent)."""
        if self._h is not None:
            h, self._h = self._h, None
            _check(library().spidar_close(h))

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def info(self):
        i = _Info()
        _check(library().spidar_get_info(self._handle(), ctypes.byref(i)))
        return {
            "protocol_version": i.protocol_version,
            "firmware_version": tuple(i.firmware_version),
            "device_id": i.device_id.decode(),
            "capabilities": i.capabilities,
            "max_blob_len": i.max_blob_len,
            "loop_period_us": i.loop_period_us,
            "strings": i.strings,
        }

    def arm(self):
        _check(library().spidar_arm(self._handle()))

    def disarm(self):
        _check(library().spidar_disarm(self._handle()))

    def heartbeat(self):
        _check(library().spidar_heartbeat(self._handle()))

    def set_force(self, fx, fy, fz):
        """Force on the end-effector, room frame, N; also the heartbeat."""
        _check(library().spidar_set_force(self._handle(), fx, fy, fz))

    def state(self):
        """The newest state, without waiting."""
        s = _State()
        _check(library().spidar_get_state(self._handle(), ctypes.byref(s)))
        return _state_dict(s)

    def wait_state(self, timeout_ms=2000):
        """The newest state, once one newer than the last one returned has
        come (waits at most timeout_ms)."""
        s = _State()
        _check(library().spidar_wait_state(self._handle(), timeout_ms, ctypes.byref(s)))
        return _state_dict(s)

    def flash(self, blob):
        """Uploads a model blob (bytes, or a path) and makes it active."""
        if not isinstance(blob, (bytes, bytearray)):
            blob = pathlib.Path(blob).read_bytes()
        m = _ModelInfo()
        _check(library().spidar_flash(self._handle(), bytes(blob), len(blob), ctypes.byref(m)))
        return _model_dict(m)

    def use_model(self, blob):
        """Says the device's model is this blob (flashed earlier)."""
        if not isinstance(blob, (bytes, bytearray)):
            blob = pathlib.Path(blob).read_bytes()
        _check(library().spidar_use_model(self._handle(), bytes(blob), len(blob)))

    def link_stats(self):
        """How the stream fared since open: states, lost, rejected,
        device_dropped (frames the device could not send because the host
        did not read in time), heartbeat_losses, loop_overruns."""
        ls = _LinkStats()
        _check(library().spidar_get_link_stats(self._handle(), ctypes.byref(ls)))
        return {name: getattr(ls, name) for name, _ in _LinkStats._fields_}

    def model_info(self):
        """The active model as a dict, or None without one."""
        m = _ModelInfo()
        _check(library().spidar_get_model_info(self._handle(), ctypes.byref(m)))
        return _model_dict(m)


def calibrate(geometry, train, test, spidar="spidar", out=None):
    """Runs the `spidar calibrate` command line (the binary `spidar`, from
    `cargo build --release -p spidar-cli`) and returns its report.json as a
    dict. Raises SpidarError with the command's message when it fails."""
    out_dir = pathlib.Path(out) if out else pathlib.Path(tempfile.mkdtemp(prefix="spidar-cal-"))
    report = out_dir / "report.json"
    cmd = [spidar, "calibrate", "--geometry", str(geometry), "--train", str(train),
           "--test", str(test), "--out", str(out_dir), "--json", str(report)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise SpidarError(r.returncode, "calibrate", r.stderr.strip() or r.stdout.strip())
    return json.loads(report.read_text())
