"""The C firmware core (``onboard/c``) built with the machine's C compiler and run in this process (software in the
loop): :class:`CFirmware` has the interface of :class:`onboard.firmware.Firmware` that the emulator drives
(``handle``, ``process_frame``, ``streaming``), so ``hostlink emulate --firmware c`` serves the same links with it.

Build: :func:`build_library` compiles ``onboard/c/*.c`` (the firmware core, shipped as package data of ``onboard``),
the generated wire codec (``hostlink.portkit.export_c``) and ``sil_binding.c`` (plain-argument entry points for
ctypes) into one shared library, once: the library is cached in the user's cache directory under the SHA-256 of every
source, the compiler and the flags, so a changed source is rebuilt and an unchanged one is loaded. The compiler is
``$CC`` or ``cc``; none is a one-line :class:`~hostlink.errors.UserError`. Flags: C99 with the flight-code warnings
as errors (:data:`WARNING_FLAGS`) and no fused multiply-add (``-ffp-contract=off``: the float32 checks are bit-exact
with numpy's, one rounding per operation).

Estimator: the core calls the estimator through ``estimator_seam.h``. When ``onboard/c/estimator_seam.c`` exists (the
numerical core's implementation) it is built; otherwise ``estimator_none.c``, and the C sensor answers READ_ESTIMATE
with NO_ESTIMATE "this sensor has no onboard estimator" (:func:`estimator_available` says which).

The platform (HAL): the flash is any :class:`onboard.banks.FlashDevice` (``RamFlash``, the emulator's ``FileFlash``)
and the identity an :class:`onboard.banks.DeviceIdentity`, both called back from C; a flash operation that raises
:class:`onboard.banks.PowerCut` is reported to the core as a power cut and raised again from the call.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from hostlink.errors import UserError
from hostlink.files.cache import cache_dir
from hostlink.portkit.export_c import firmware_core_files, generate_c
from onboard import banks
from onboard.firmware import Counters, EstimatorBudget
from onboard.params import CameraParams, PlausibilityLimits
from protocol import messages as m

#: Warnings the core is held to (flight-code habits); the build treats each as an error.
WARNING_FLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-Wconversion", "-Wshadow")
#: Code generation: position-independent, optimised, no fused multiply-add (bit-exact float32 with numpy).
CODE_FLAGS = ("-O2", "-fPIC", "-ffp-contract=off")
#: The sanitized build (``load_library(sanitize=True)``): AddressSanitizer and UndefinedBehaviorSanitizer, every
#: finding fatal. Loading it into Python needs the ASan runtime preloaded (:func:`sanitizer_preload`).
SANITIZE_FLAGS = ("-fsanitize=address,undefined", "-fno-sanitize-recover=all", "-fno-omit-frame-pointer", "-g")
#: The binding's source (not part of the core).
BINDING_SOURCE = "sil_binding.c"
#: Reply buffer [bytes]: firmware.h's FIRMWARE_REPLY_MAX_BYTES (a Nak with its longest text).
REPLY_CAP = 126
#: Result codes of firmware_handle (firmware.h).
_REPLY, _UNDECODABLE, _POWER_CUT = 0, 1, 2

_READ = ctypes.CFUNCTYPE(
    ctypes.c_int, ctypes.c_void_p, ctypes.c_uint32, ctypes.POINTER(ctypes.c_uint8), ctypes.c_uint32
)
_ERASE = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_uint32)
_PROGRAM = ctypes.CFUNCTYPE(
    ctypes.c_int, ctypes.c_void_p, ctypes.c_uint32, ctypes.POINTER(ctypes.c_uint8), ctypes.c_uint32
)
_RANDOM = ctypes.CFUNCTYPE(ctypes.c_uint32, ctypes.c_void_p)


# ------------------------------------------------------------------------------------------------------ sources
def core_sources() -> dict[str, str]:
    """File name -> text of the firmware core as shipped (``hostlink.portkit.export_c.firmware_core_files``)."""
    return firmware_core_files()


def estimator_available() -> bool:
    """Whether the shipped core has an estimator implementation (``estimator_seam.c``)."""
    return "estimator_seam.c" in core_sources()


def find_compiler() -> str:
    """``$CC`` or ``cc`` on PATH; a one-line UserError when there is none."""
    name = os.environ.get("CC") or "cc"
    path = shutil.which(name)
    if path is None:
        raise UserError(
            f"no C compiler found ({name!r} is not on PATH): install one (e.g. gcc) or use --firmware python"
        )
    return path


def _cache_root() -> Path:
    return cache_dir() / "firmware-c"


def build_sources() -> dict[str, str]:
    """Every file the library is built from: the core, the generated codec and the binding (C sources and headers
    only: the core's README is shipped with it but compiles to nothing, so an edit of it keeps the cached build)."""
    binding = resources.files("hostlink.portkit").joinpath(BINDING_SOURCE).read_text()
    code = {name: text for name, text in core_sources().items() if name.endswith((".c", ".h"))}
    return {**code, **generate_c(), BINDING_SOURCE: binding}


def compile_command(compiler: str, directory: Path, output: Path, extra: tuple[str, ...] = ()) -> list[str]:
    """The compiler call that builds the shared library from the sources written in ``directory``."""
    sources = sorted(str(p) for p in directory.glob("*.c"))
    return [
        compiler,
        *WARNING_FLAGS,
        *CODE_FLAGS,
        *extra,
        "-shared",
        f"-I{directory}",
        *sources,
        "-o",
        str(output),
        "-lm",
    ]


def build_library(cache: Path | None = None, extra: tuple[str, ...] = ()) -> Path:
    """The shared library of the current sources (``extra``: more compiler flags, e.g. :data:`SANITIZE_FLAGS`):
    loaded from the cache when built before, else compiled once (into a temporary file, then renamed: a concurrent
    build never leaves a half-written library). A compiler error is a UserError carrying its first lines."""
    compiler = find_compiler()
    sources = build_sources()
    digest = hashlib.sha256()
    for name, text in sources.items():
        digest.update(name.encode() + b"\0" + text.encode() + b"\0")
    digest.update(" ".join((compiler, *WARNING_FLAGS, *CODE_FLAGS, *extra)).encode())
    root = _cache_root() if cache is None else Path(cache)
    library = root / f"stfirmware-{digest.hexdigest()[:24]}.so"
    if library.is_file():
        return library
    try:
        root.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=root, prefix="build-") as tmp:
            work = Path(tmp)
            for name, text in sources.items():
                (work / name).write_text(text)
            partial = work / "lib.so"
            run = subprocess.run(compile_command(compiler, work, partial, extra), capture_output=True, text=True)
            if run.returncode != 0:
                said = (run.stderr or run.stdout).strip().splitlines()[:3]
                first = " | ".join(said) if said else f"exit status {run.returncode}, no message"
                raise UserError(f"the C firmware core did not compile with {compiler}: {first}")
            if not partial.is_file():
                raise UserError(f"the C firmware core did not compile with {compiler}: it wrote no library")
            os.replace(partial, library)
    except OSError as exc:
        raise UserError(f"cannot build the C firmware core in {root}: {exc.strerror or exc}") from exc
    return library


_LIBRARIES: dict[tuple[Path | None, bool], ctypes.CDLL] = {}


def sanitizer_preload() -> str | None:
    """The AddressSanitizer runtime of the compiler (``cc -print-file-name=libasan.so``), which must be in
    ``LD_PRELOAD`` of a Python process that loads the sanitized build; None when the compiler has none."""
    run = subprocess.run([find_compiler(), "-print-file-name=libasan.so"], capture_output=True, text=True)
    path = run.stdout.strip()
    return path if run.returncode == 0 and os.path.isabs(path) and os.path.isfile(path) else None


def load_library(cache: Path | None = None, sanitize: bool = False) -> ctypes.CDLL:
    """The built library, built or found and loaded once per process and cache (the shipped sources do not change
    while it runs), with its functions' signatures declared. ``sanitize``: the build with :data:`SANITIZE_FLAGS`
    (the process must run with :func:`sanitizer_preload` in ``LD_PRELOAD``)."""
    lib = _LIBRARIES.get((cache, sanitize))
    if lib is not None:
        return lib
    path = build_library(cache, SANITIZE_FLAGS if sanitize else ())
    try:
        lib = ctypes.CDLL(str(path))
    except OSError as exc:
        raise UserError(f"the C firmware core built as {path} does not load: {exc}") from exc
    p_u8 = ctypes.POINTER(ctypes.c_uint8)
    p_f64 = ctypes.POINTER(ctypes.c_double)
    lib.sil_firmware_bytes.restype = ctypes.c_size_t
    lib.sil_estimator_bytes.restype = ctypes.c_size_t
    lib.sil_boot.argtypes = [
        ctypes.c_void_p, _READ, _ERASE, _PROGRAM, _RANDOM, p_u8, ctypes.c_uint32, ctypes.c_double, ctypes.c_double,
        ctypes.c_double, ctypes.c_char_p, ctypes.c_uint32, p_u8, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32,
        ctypes.c_double, ctypes.c_double, ctypes.c_double, ctypes.c_double,
    ]  # fmt: skip
    lib.sil_handle.argtypes = [
        ctypes.c_void_p, p_u8, ctypes.c_size_t, p_u8, ctypes.c_size_t, ctypes.POINTER(ctypes.c_size_t)
    ]  # fmt: skip
    lib.sil_process_frame.argtypes = [
        ctypes.c_void_p, ctypes.c_uint32, ctypes.c_int64, ctypes.c_uint32, ctypes.POINTER(ctypes.c_uint32), p_f64,
        p_f64, p_f64,
    ]  # fmt: skip
    lib.sil_set_next_frame.argtypes = [ctypes.c_void_p, ctypes.c_uint32]
    lib.sil_state.argtypes = [ctypes.c_void_p, p_u8, ctypes.POINTER(ctypes.c_uint32)]
    lib.sil_check_table.argtypes = [
        p_u8, ctypes.c_uint32, ctypes.c_double, ctypes.c_uint32, ctypes.c_char_p, ctypes.POINTER(ctypes.c_uint32)
    ]  # fmt: skip
    lib.sil_format.argtypes = [ctypes.c_uint32, ctypes.c_double, ctypes.c_char_p]
    lib.sil_format.restype = ctypes.c_uint32
    _LIBRARIES[(cache, sanitize)] = lib
    return lib


# -------------------------------------------------------------------------------------------------------- binding
def _u8(data: bytes) -> ctypes.Array:
    return (ctypes.c_uint8 * max(1, len(data))).from_buffer_copy(bytes(data) or b"\0")


@dataclass
class _Hal:
    """The Python side of the core's HAL: flash callbacks and the random source, kept alive with the firmware."""

    flash: banks.FlashDevice
    identity: banks.DeviceIdentity
    power_cut: banks.PowerCut | None = None

    def callbacks(self) -> tuple:
        def read(_ctx, address, out, n):
            try:
                ctypes.memmove(out, self.flash.read(int(address), int(n)), int(n))
                return 0
            except Exception:  # noqa: BLE001 - nothing may cross back into C as an exception
                return 1

        def erase(_ctx, sector):
            return self._flash_op(lambda: self.flash.erase(int(sector)))

        def program(_ctx, address, data, n):
            raw = ctypes.string_at(data, int(n))
            return self._flash_op(lambda: self.flash.program(int(address), raw))

        def random32(_ctx):
            return int(self.identity.random32()) & 0xFFFFFFFF

        return _READ(read), _ERASE(erase), _PROGRAM(program), _RANDOM(random32)

    def _flash_op(self, op) -> int:
        try:
            op()
            return 0
        except banks.PowerCut as cut:
            self.power_cut = cut
            return 1


class CFirmware:
    """The C firmware core behind the Python firmware's interface (``handle``, ``process_frame``, ``streaming``,
    ``counters``). ``factory``: program this set as generation 1 first (``onboard.banks.factory_store``), else boot
    what ``flash`` holds. Without an estimator implementation in the build, the sensor has none (``estimator`` is
    then ignored: READ_ESTIMATE answers NO_ESTIMATE). ``drift_focal_mm_per_frame``: the estimator's focal random walk
    (``estimator_seam_config_t``; 0: the C default, 7e-5 mm)."""

    def __init__(
        self,
        flash: banks.FlashDevice,
        identity: banks.DeviceIdentity,
        limits: PlausibilityLimits | None,
        factory: CameraParams | None = None,
        budget: EstimatorBudget | None = None,
        estimate_mask: int = 0,
        precision: str = "float32",
        centroid_noise_px: float = 0.05,
        drift_focal_mm_per_frame: float = 0.0,
        with_estimator: bool = True,
        library: ctypes.CDLL | None = None,
    ) -> None:
        self._lib = load_library() if library is None else library
        self._hal = _Hal(flash, identity)
        self._callbacks = self._hal.callbacks()
        self._fw = ctypes.create_string_buffer(int(self._lib.sil_firmware_bytes()) + 16)
        self.has_estimator = bool(with_estimator and self._lib.sil_estimator_available())
        self._est = (
            ctypes.create_string_buffer(int(self._lib.sil_estimator_bytes()) + 16) if self.has_estimator else None
        )
        budget = budget or EstimatorBudget()
        self._design_name = (limits.design_name if limits else "design value").encode()
        table = _u8(banks.params_to_table(factory)) if factory is not None else None
        result = self._lib.sil_boot(
            _aligned(self._fw), *self._callbacks, _u8(identity.uid), int(limits is not None),
            limits.design_focal_length_mm if limits else 0.0, limits.focal_tolerance if limits else 0.0,
            limits.max_distortion_fraction if limits else 0.0, self._design_name,
            int(limits is not None and limits.fixed_point), table,
            _aligned(self._est) if self._est is not None else None, estimate_mask,
            {"float32": 0, "fixed": 1}[precision], centroid_noise_px, drift_focal_mm_per_frame, budget.flops_per_s,
            budget.min_frame_period_s,
        )  # fmt: skip
        self._raise_power_cut()
        if result == 2:
            raise RuntimeError("the flash could not be read while booting the C firmware")
        if result != 0:
            raise ValueError("the estimator budget needs flops_per_s > 0 and min_frame_period_s > 0")
        self.flash = flash

    def _raise_power_cut(self) -> None:
        cut, self._hal.power_cut = self._hal.power_cut, None
        if cut is not None:
            raise cut

    def handle_bytes(self, data: bytes) -> bytes | None:
        """One command message's bytes -> the reply's bytes, or None when they are not a message (as a transport
        drops them). A power cut raises :class:`onboard.banks.PowerCut`."""
        reply = (ctypes.c_uint8 * REPLY_CAP)()
        n = ctypes.c_size_t(0)
        result = self._lib.sil_handle(_aligned(self._fw), _u8(data), len(data), reply, REPLY_CAP, ctypes.byref(n))
        self._raise_power_cut()
        if result == _UNDECODABLE:
            return None
        if result != _REPLY:
            raise RuntimeError(f"firmware_handle returned {result}")
        return bytes(reply[: n.value])

    def handle(self, command: m.Message) -> m.Message:
        """One decoded command -> its decoded reply (as :meth:`onboard.firmware.Firmware.handle`)."""
        return m.decode(self.handle_bytes(m.encode(command)))

    def process_frame(self, frame: m.CentroidFrame, r_ref: np.ndarray | None) -> bool:
        """One exposure (as :meth:`onboard.firmware.Firmware.process_frame`)."""
        n = int(frame.n_stars)
        ids = np.ascontiguousarray(np.asarray(frame.star_id, dtype=np.uint32).reshape(n))
        x = np.ascontiguousarray(np.asarray(frame.x_px, dtype=np.float64).reshape(n))
        y = np.ascontiguousarray(np.asarray(frame.y_px, dtype=np.float64).reshape(n))
        r = None if r_ref is None else np.ascontiguousarray(np.asarray(r_ref, dtype=np.float64).reshape(n, 3))
        p_f64 = ctypes.POINTER(ctypes.c_double)
        ran = self._lib.sil_process_frame(
            _aligned(self._fw), int(frame.frame) & 0xFFFFFFFF, int(frame.t_us), n,
            ids.ctypes.data_as(ctypes.POINTER(ctypes.c_uint32)), x.ctypes.data_as(p_f64), y.ctypes.data_as(p_f64),
            None if r is None else r.ctypes.data_as(p_f64),
        )  # fmt: skip
        return bool(ran)

    def set_next_frame(self, frame: int) -> None:
        """The camera's counter of the next exposure (as :meth:`onboard.firmware.Firmware.set_next_frame`)."""
        self._lib.sil_set_next_frame(_aligned(self._fw), int(frame) & 0xFFFFFFFF)

    def _state(self) -> tuple[bool, list[int]]:
        streaming = ctypes.c_uint8(0)
        out = (ctypes.c_uint32 * 8)()
        self._lib.sil_state(_aligned(self._fw), ctypes.byref(streaming), out)
        return bool(streaming.value), list(out)

    @property
    def streaming(self) -> bool:
        return self._state()[0]

    @property
    def counters(self) -> Counters:
        values = self._state()[1]
        return Counters(*values[:5])

    @property
    def nonce_counter(self) -> int:
        return self._state()[1][5]

    @property
    def epoch(self) -> int:
        return self._state()[1][7]


def _aligned(buffer: ctypes.Array | None) -> int | None:
    """The 16-byte aligned address inside a buffer allocated 16 bytes larger (the firmware struct holds doubles)."""
    if buffer is None:
        return None
    address = ctypes.addressof(buffer)
    return address + (-address % 16)


def check_table_c(table: bytes, limits: PlausibilityLimits | None) -> str | None:
    """The C core's verdict on a table (``params_check_table``): None if usable, else the refusal text (the default
    tolerances; ``limits`` gives the design focal length)."""
    lib = load_library()
    text = ctypes.create_string_buffer(128)
    n = ctypes.c_uint32(0)
    bad = lib.sil_check_table(
        _u8(table),
        int(limits is not None),
        limits.design_focal_length_mm if limits else 0.0,
        int(limits is not None and limits.fixed_point),
        text,
        ctypes.byref(n),
    )
    return text.raw[: n.value].decode() if bad else None


#: pyformat.h's formats, in sil_format's order, as Python spells them.
FORMATS = ("r", ".3g", ".6g", ".0f", ".0%")


def format_c(spec: str, x: float) -> str:
    """The C core's formatting of ``x`` with the f-string ``spec`` (one of :data:`FORMATS`: "r" = repr)."""
    text = ctypes.create_string_buffer(128)
    n = load_library().sil_format(FORMATS.index(spec), float(x), text)
    return text.raw[:n].decode()
