"""The C firmware core on an emulated Cortex-M (processor in the loop, no board): cross-compiled for the target,
loaded into an instruction-set emulator, called function by function, its size, stack and instructions measured
(``hostlink costs --target cortex-m4f``; docs/port-kit.md section "The core on a Cortex-M").

Toolchain (the optional ``cortexm`` extra, ``pip install 'startracker-companion[cortexm]'``): the ``ziglang`` wheel
(clang and lld for ``thumb`` targets, with a compiler runtime: soft float, sqrt, sin, cos, tan, floor, ceil, round,
memcpy, memset) and ``unicorn`` (QEMU's ARM translator as a library: Cortex-M0 and Cortex-M4 models, hooks on every
translated block). Both are Python wheels, so nothing but pip is needed; Debian's gcc-arm-none-eabi and
qemu-system-arm would need root and give no per-instruction count. The two C library functions the runtime lacks
come from the musl sources the wheel ships (pow, ldexp: built with the same target flags) and from
``cortexm_glue.c`` (frexp, the flash HAL of the measurement).

Build (:func:`build_image`): every ``onboard/c`` file, the generated wire codec (``hostlink export-c``), the SIL
binding (``sil_binding.c``, the core's structs as plain arguments) and the glue, compiled with the flight-code flags
(C99, ``-Werror``, no fused multiply-add) and ``-O2``, each function in its own section, linked by lld with a
linker script that keeps every function of the core and drops unused runtime (flash from 0x08000000, RAM from
0x20000000). The ELF is cached under a hash of the sources, flags and toolchain version.

Measurement (:class:`Machine`): the emulator runs one call at a time, the arguments placed per the AAPCS (the
``-eabihf`` VFP variant on the M4F); data the host passes lives in a scratch region outside the image. Instructions
are counted exactly (every executed translated block adds its instruction count, decoded from the Thumb encoding:
stable run to run). Unicorn has no timing model: on the Cortex-M0+, whose timing is fixed per instruction, cycles
are added from the TRM's table (:func:`m0plus_cycles`, zero-wait-state memory, the single-cycle multiplier; a
conditional branch's outcome from the next block's address); on the M4F (pipelined loads, variable-latency divide,
branch refill) they are not modelled: ``None``. The stack's high-water mark: the
stack region is painted before a call and the deepest overwritten word found after it.
"""

from __future__ import annotations

import ctypes
import hashlib
import json
import os
import struct
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from hostlink.errors import UserError
from hostlink.files.cache import cache_dir

#: Image memory map (an STM32F4-like part; sizes generous: the measurement reports what the image needs).
FLASH_BASE, FLASH_MAP_BYTES = 0x0800_0000, 2 << 20
RAM_BASE, RAM_MAP_BYTES = 0x2000_0000, 512 << 10
#: Stack: the top of the mapped RAM, this much painted below it.
STACK_PAINT_BYTES = 64 << 10
STACK_TOP = RAM_BASE + RAM_MAP_BYTES
#: Scratch region for the host's arguments (not part of the image) and the flash device of the banks' HAL.
SCRATCH_BASE, SCRATCH_BYTES = 0x4000_0000, 1 << 20
FLASH_DEVICE_BASE, FLASH_DEVICE_BYTES = 0x6000_0000, 64 << 10
_PAINT = 0xA5
#: Code generation on top of the flight-code warnings (firmware_c.WARNING_FLAGS): optimised, one section per
#: function and object (the linker keeps the core's and drops unused runtime), no fused multiply-add.
#: Optimisation levels ``--optimise`` offers (-O2: the host build's; -Os: for size, as flight images often are).
OPTIMISE = ("O2", "Os")
CODE_FLAGS = (
    "-ffp-contract=off",
    "-ffunction-sections",
    "-fdata-sections",
    "-fno-stack-protector",
    "-fomit-frame-pointer",
)
#: The musl sources (in the ziglang wheel) of the libm functions the compiler runtime does not supply.
MUSL_MATH = (
    "pow",
    "pow_data",
    "exp_data",
    "__math_oflow",
    "__math_uflow",
    "__math_xflow",
    "__math_invalid",
    "__math_divzero",
    "scalbn",
    "ldexp",
)
GLUE_SOURCE = "cortexm_glue.c"
BINDING_SOURCE = "sil_binding.c"


@dataclass(frozen=True)
class Target:
    """One Cortex-M target: its compiler triple and CPU, the emulator's CPU model, the estimator precision it runs
    and the clock the docs quote times at."""

    name: str
    triple: str
    cpu: str
    hard_float: bool
    unicorn_cpu: str
    precision: str
    clock_hz: float
    description: str
    cycles_modelled: bool = False


TARGETS: dict[str, Target] = {
    "cortex-m4f": Target(
        "cortex-m4f",
        "thumb-freestanding-eabihf",
        "cortex_m4+vfp4d16sp",
        True,
        "UC_CPU_ARM_CORTEX_M4",
        "float32",
        168e6,
        "ARMv7E-M with the single-precision FPU (FPv4-SP-D16), hard-float ABI; float32 filter on the FPU",
    ),
    "cortex-m0plus": Target(
        "cortex-m0plus",
        "thumb-freestanding-eabi",
        "cortex_m0plus",
        False,
        "UC_CPU_ARM_CORTEX_M0",
        "fixed",
        64e6,
        "ARMv6-M, no FPU: the fixed-point front end in integers, the filter in soft float32",
        cycles_modelled=True,
    ),
}


def target(name: str) -> Target:
    if name not in TARGETS:
        raise UserError(f"unknown target {name!r}: choose one of {', '.join(TARGETS)}")
    return TARGETS[name]


# ------------------------------------------------------------------------------------------------- toolchain
def require_tools():
    """(ziglang directory, unicorn module), or a one-line UserError naming the extra to install."""
    try:
        import unicorn
        import ziglang
    except ImportError as exc:
        raise UserError(
            f"--target needs the cross compiler and emulator ({exc.name} is not installed): "
            "pip install 'startracker-companion[cortexm]'"
        ) from None
    return Path(ziglang.__file__).parent, unicorn


def tools_available() -> bool:
    try:
        require_tools()
    except UserError:
        return False
    return True


def _zig(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "ziglang", *args], cwd=cwd, capture_output=True, text=True, timeout=900
    )


def _cache_root() -> Path:
    return cache_dir() / "cortexm"


_LINKER_SCRIPT = f"""
MEMORY {{
  FLASH (rx) : ORIGIN = {FLASH_BASE:#x}, LENGTH = {FLASH_MAP_BYTES}
  RAM (rwx) : ORIGIN = {RAM_BASE:#x}, LENGTH = {RAM_MAP_BYTES - STACK_PAINT_BYTES}
}}
SECTIONS {{
  .text : {{ KEEP(*core_*.o(.text .text.*)) KEEP(*glue_*.o(.text .text.*)) *(.text .text.*) }} > FLASH
  .rodata : {{ KEEP(*core_*.o(.rodata .rodata.*)) *(.rodata .rodata.*) }} > FLASH
  .ARM.exidx : {{ *(.ARM.exidx*) }} > FLASH
  .data : {{ KEEP(*core_*.o(.data .data.*)) *(.data .data.*) }} > RAM AT > FLASH
  .bss (NOLOAD) : {{ KEEP(*core_*.o(.bss .bss.* COMMON)) KEEP(*glue_*.o(.bss .bss.*)) *(.bss .bss.* COMMON) }} > RAM
}}
"""


def image_sources() -> dict[str, str]:
    """File name -> text of everything the image is built from: the core (as the host build takes it), the
    generated codec, the SIL binding and the glue."""
    from hostlink.portkit import firmware_c

    portkit = resources.files("hostlink.portkit")
    return {
        **firmware_c.build_sources(),
        BINDING_SOURCE: portkit.joinpath(BINDING_SOURCE).read_text(),
        GLUE_SOURCE: portkit.joinpath(GLUE_SOURCE).read_text(),
    }


def build_image(tgt: Target, optimise: str = "O2") -> Path:
    """The target's ELF image, built once per sources and toolchain (cached); a compile or link error is a
    one-line UserError with the compiler's first lines."""
    from hostlink.portkit.firmware_c import WARNING_FLAGS

    zig_dir, _ = require_tools()
    sources = image_sources()
    version = _zig("version", cwd=Path(tempfile.gettempdir())).stdout.strip()
    digest = hashlib.sha256()
    for name, text in sorted(sources.items()):
        digest.update(name.encode() + b"\0" + text.encode() + b"\0")
    if optimise not in OPTIMISE:
        raise UserError(f"--optimise must be one of {', '.join(OPTIMISE)}, got {optimise!r}")
    flags = (*CODE_FLAGS, f"-{optimise}")
    digest.update(" ".join((version, tgt.triple, tgt.cpu, *WARNING_FLAGS, *flags, *MUSL_MATH)).encode())
    digest.update(_LINKER_SCRIPT.encode() + b"with its map")
    root = _cache_root()
    elf = root / f"{tgt.name}-{optimise}-{digest.hexdigest()[:24]}.elf"
    if elf.is_file():
        return elf
    root.mkdir(parents=True, exist_ok=True)
    musl = zig_dir / "lib" / "libc" / "musl"
    headers = zig_dir / "lib" / "libc" / "include"
    target_flags = ["-target", tgt.triple, f"-mcpu={tgt.cpu}"]
    libc_headers = ["-isystem", str(headers / "generic-musl"), "-isystem", str(headers / "arm-linux-musl")]
    with tempfile.TemporaryDirectory(dir=root, prefix="build-") as tmp:
        work = Path(tmp)
        for name, text in sources.items():
            (work / name).write_text(text)
        objects = []
        for name in sorted(n for n in sources if n.endswith(".c")):
            obj = (
                work / f"core_{name[:-2]}.o"
                if name not in (GLUE_SOURCE, BINDING_SOURCE)
                else work / f"glue_{name[:-2]}.o"
            )
            cmd = [
                "cc",
                *target_flags,
                *WARNING_FLAGS,
                *flags,
                *libc_headers,
                f"-I{work}",
                "-c",
                name,
                "-o",
                str(obj),
            ]
            _checked(_zig(*cmd, cwd=work), f"{name} did not compile for {tgt.name}")
            objects.append(obj)
        for name in MUSL_MATH:
            obj = work / f"libm_{name}.o"
            cmd = [
                "cc",
                *target_flags,
                f"-{optimise}",
                "-ffunction-sections",
                "-w",
                *libc_headers,
                f"-I{musl / 'src' / 'include'}",
                f"-I{musl / 'src' / 'internal'}",
                f"-I{musl / 'arch' / 'arm'}",
                f"-I{musl / 'arch' / 'generic'}",
                "-c",
                str(musl / "src" / "math" / f"{name}.c"),
                "-o",
                str(obj),
            ]
            _checked(_zig(*cmd, cwd=work), f"musl's {name}.c did not compile for {tgt.name}")
            objects.append(obj)
        (work / "image.ld").write_text(_LINKER_SCRIPT)
        out = work / "image.elf"
        cmd = ["cc", *target_flags, "-nostartfiles", "-T", "image.ld", "-Wl,--gc-sections", "-Wl,--no-entry"]
        _checked(_zig(*cmd, *map(str, objects), "-o", str(out), cwd=work), f"the {tgt.name} image did not link")
        origins = {str(o.name): sorted(read_elf(o).symbols) for o in objects}
        elf.with_suffix(".symbols.json").write_text(json.dumps(origins))
        os.replace(out, elf)
    return elf


def _checked(run: subprocess.CompletedProcess, what: str) -> None:
    if run.returncode != 0:
        lines = [ln for ln in (run.stderr or run.stdout).strip().splitlines() if ln.strip()]
        raise UserError(f"{what}: {' | '.join(lines[:3])}")


def flash_breakdown(elf: Path) -> dict[str, int]:
    """Flash bytes by origin: "core" (onboard/c), "codec" (the generated wire codec), "binding and glue"
    (sil_binding.c, cortexm_glue.c: not flight code) as the sizes of the image's functions and objects each object
    file defines (recorded at the build), "runtime" the rest (the compiler runtime: soft float, 64-bit division,
    the libm functions, memcpy/memset; and alignment padding)."""
    image = read_elf(elf)
    origins = json.loads(Path(elf).with_suffix(".symbols.json").read_text())
    out = {"core": 0, "codec": 0, "binding and glue": 0}
    seen: set[str] = set()
    for obj, names in origins.items():
        key = "codec" if obj.startswith("core_st_") else "core" if obj.startswith("core_") else None
        key = "binding and glue" if obj.startswith("glue_") else key
        if key is None:
            continue
        for name in names:
            if name in image.symbols and name not in seen and not name.startswith("$"):
                seen.add(name)
                out[key] += image.symbols[name][1]
    out["runtime"] = image.flash_bytes - sum(out.values())
    return out


# ------------------------------------------------------------------------------------------------------ ELF
@dataclass(frozen=True)
class Image:
    """A linked ELF: its loadable segments (address, bytes, memory size), symbols (name -> (address, size)) and
    section sizes (name -> bytes)."""

    segments: tuple[tuple[int, bytes, int], ...]
    symbols: dict[str, tuple[int, int]]
    sections: dict[str, int]

    @property
    def flash_bytes(self) -> int:
        """What the part's flash holds: code, read-only data, unwind index and the initial values of .data."""
        return sum(self.sections.get(s, 0) for s in (".text", ".rodata", ".ARM.exidx", ".data"))

    @property
    def ram_bytes(self) -> int:
        """Static RAM: .data + .bss (the stack is measured separately)."""
        return self.sections.get(".data", 0) + self.sections.get(".bss", 0)


def read_elf(path: Path) -> Image:
    """The ELF32 little-endian ARM image at ``path`` (program headers, section headers, the symbol table)."""
    raw = Path(path).read_bytes()
    if raw[:4] != b"\x7fELF" or raw[4] != 1 or raw[5] != 1:
        raise UserError(f"{path}: not a 32-bit little-endian ELF")
    phoff, shoff = struct.unpack_from("<II", raw, 28)
    phentsize, phnum, shentsize, shnum, shstrndx = struct.unpack_from("<HHHHH", raw, 42)
    segments = []
    for i in range(phnum):
        p_type, off, vaddr, _paddr, filesz, memsz, _flags, _align = struct.unpack_from(
            "<8I", raw, phoff + i * phentsize
        )
        if p_type == 1:  # PT_LOAD
            segments.append((vaddr, raw[off : off + filesz], memsz))
    headers = [struct.unpack_from("<10I", raw, shoff + i * shentsize) for i in range(shnum)]
    shstr = headers[shstrndx][4]

    def name_at(table_offset: int, index: int) -> str:
        start = table_offset + index
        return raw[start : raw.index(b"\0", start)].decode()

    sections, symbols = {}, {}
    for h in headers:
        sections[name_at(shstr, h[0])] = h[5]
        if h[1] == 2:  # SHT_SYMTAB
            strtab = headers[h[6]][4]
            for k in range(h[5] // 16):
                st_name, value, size, _info, _other, _shndx = struct.unpack_from("<IIIBBH", raw, h[4] + 16 * k)
                name = name_at(strtab, st_name)
                if name:
                    symbols[name] = (value, size)
    return Image(tuple(segments), symbols, sections)


# ------------------------------------------------------------------------------------------------ the machine
def thumb_decode(code: bytes):
    """The instructions of a run of Thumb code as (offset, first halfword, second halfword or None): a halfword
    whose top five bits are 0b11101, 0b11110 or 0b11111 starts a 32-bit instruction (ARMv7-M ARM A5.1), any other a
    16-bit one."""
    i = 0
    while i + 1 < len(code):
        first = code[i] | code[i + 1] << 8
        wide = (first >> 11) in (0b11101, 0b11110, 0b11111)
        second = (code[i + 2] | code[i + 3] << 8) if wide and i + 3 < len(code) else None
        yield i, first, second
        i += 4 if wide else 2


def thumb_instructions(code: bytes) -> int:
    """Instructions in a run of Thumb code (:func:`thumb_decode`)."""
    return sum(1 for _ in thumb_decode(code))


def m0plus_cycles(halfword: int, second: int | None = None) -> tuple[int, bool]:
    """Cycles of one ARMv6-M instruction on a Cortex-M0+ with zero-wait-state memory and the single-cycle multiplier
    (Cortex-M0+ Technical Reference Manual, ARM DDI 0484C, table 3-1 "Cortex-M0+ instruction summary"), and
    whether it is a conditional branch (then this is the not-taken count; taken costs one more). ``halfword``: the
    first 16 bits, ``second``: the next 16 for a 32-bit instruction.

    Loads and stores 2; LDM/STM/PUSH 1 + N; POP 1 + N, POP with PC 3 + N (N registers besides PC); B<cond> 1 not
    taken, 2 taken; B 2; BX, BLX 2; ADD or MOV to PC 2; BL 3; MSR, MRS 3, DMB/DSB/ISB 3 (32-bit); every other
    instruction 1 (data processing, MULS)."""
    h = halfword
    if second is not None:
        if (h & 0xF800) == 0xF000 and (second & 0xD000) == 0xD000:
            return 3, False  # BL
        return 3, False  # MSR, MRS, DMB, DSB, ISB (ARMv6-M's other 32-bit instructions)
    if 0x4800 <= h <= 0x9FFF:  # LDR literal, LDR/STR register, immediate, halfword, SP-relative
        return 2, False
    if (h & 0xFE00) == 0xB400:  # PUSH
        return 1 + bin(h & 0x1FF).count("1"), False
    if (h & 0xFE00) == 0xBC00:  # POP
        n = bin(h & 0xFF).count("1")
        return (3 + n, False) if h & 0x100 else (1 + n, False)
    if (h & 0xF000) == 0xC000:  # LDM, STM
        return 1 + bin(h & 0xFF).count("1"), False
    if (h & 0xF000) == 0xD000 and (h & 0x0F00) < 0x0E00:  # B<cond>
        return 1, True
    if (h & 0xF800) == 0xE000:  # B
        return 2, False
    if (h & 0xFF00) == 0x4700:  # BX, BLX
        return 2, False
    if (h & 0xFF00) in (0x4400, 0x4600) and (h & 0x87) == 0x87:  # ADD / MOV with the PC as destination
        return 2, False
    return 1, False


@dataclass(frozen=True)
class Call:
    """What one call cost: instructions executed, the deepest stack [bytes] below the caller's stack pointer, and
    cycles where the target's timing is modelled (the Cortex-M0+; None on the M4F)."""

    instructions: int
    stack_bytes: int
    cycles: int | None = None


class Arg:
    """A scalar argument of a given C type: "i32", "u32", "i64", "u64", "f32", "f64"."""

    def __init__(self, ctype: str, value) -> None:
        self.ctype, self.value = ctype, value


class Machine:
    """The target's image loaded into a unicorn Cortex-M, ready for calls (:meth:`call`)."""

    def __init__(self, tgt: Target, optimise: str = "O2") -> None:
        _, unicorn = require_tools()
        from unicorn import arm_const

        self.target = tgt
        self.elf = build_image(tgt, optimise)
        self.optimise = optimise
        self.image = read_elf(self.elf)
        self._arm = arm_const
        uc = unicorn.Uc(unicorn.UC_ARCH_ARM, unicorn.UC_MODE_THUMB | unicorn.UC_MODE_MCLASS)
        uc.ctl_set_cpu_model(getattr(arm_const, tgt.unicorn_cpu))
        uc.mem_map(FLASH_BASE, FLASH_MAP_BYTES)
        uc.mem_map(RAM_BASE, RAM_MAP_BYTES)
        uc.mem_map(SCRATCH_BASE, SCRATCH_BYTES)
        uc.mem_map(FLASH_DEVICE_BASE, FLASH_DEVICE_BYTES)
        for address, data, memsz in self.image.segments:
            uc.mem_write(address, data + bytes(memsz - len(data)))
        uc.mem_write(FLASH_DEVICE_BASE, b"\xff" * FLASH_DEVICE_BYTES)
        if tgt.hard_float:  # the reset handler's job on a real part: CPACR CP10/CP11 full access, FPEXC.EN
            uc.reg_write(arm_const.UC_ARM_REG_C1_C0_2, uc.reg_read(arm_const.UC_ARM_REG_C1_C0_2) | (0xF << 20))
            uc.reg_write(arm_const.UC_ARM_REG_FPEXC, 0x4000_0000)
        self.uc = uc
        self._blocks: dict[tuple[int, int], tuple[int, int, int | None]] = {}
        self._count = 0
        self._cycles = 0
        self._pending_fallthrough: int | None = None  # a block ended in a conditional branch: its not-taken address
        self.models_cycles = tgt.cycles_modelled
        uc.hook_add(unicorn.UC_HOOK_BLOCK, self._on_block)
        self._return = self.address("cortexm_return")
        self._scratch = SCRATCH_BASE

    def _on_block(self, uc, address, size, _data) -> None:
        key = (address, size)
        block = self._blocks.get(key)
        if block is None:
            block = self._decode_block(bytes(uc.mem_read(address, size)), address)
            self._blocks[key] = block
        if self._pending_fallthrough is not None:  # the previous block's conditional branch: taken costs one more
            self._cycles += int(address != self._pending_fallthrough)
            self._pending_fallthrough = None
        n, cycles, fallthrough = block
        self._count += n
        self._cycles += cycles
        self._pending_fallthrough = fallthrough

    def _decode_block(self, code: bytes, address: int) -> tuple[int, int, int | None]:
        """(instructions, cycles with a final conditional branch not taken, that branch's not-taken address)."""
        n = cycles = 0
        fallthrough = None
        for offset, first, second in thumb_decode(code):
            c, conditional = m0plus_cycles(first, second) if self.models_cycles else (0, False)
            n += 1
            cycles += c
            fallthrough = address + offset + (2 if second is None else 4) if conditional else None
        return n, cycles, fallthrough

    def address(self, symbol: str) -> int:
        if symbol not in self.image.symbols:
            raise UserError(f"the {self.target.name} image has no symbol {symbol!r}")
        return self.image.symbols[symbol][0] & ~1  # a Thumb function's symbol has bit 0 set

    # ------------------------------------------------------------------ memory
    def reset_scratch(self) -> None:
        self._scratch = SCRATCH_BASE

    def alloc(self, n_bytes: int, data: bytes | None = None) -> int:
        """n_bytes of scratch (8-aligned), zeroed or set to ``data``; freed by :meth:`reset_scratch`."""
        address = self._scratch
        self._scratch = (address + max(int(n_bytes), 1) + 7) & ~7
        if self._scratch > SCRATCH_BASE + SCRATCH_BYTES:
            raise MemoryError("scratch region exhausted")
        self.uc.mem_write(address, bytes(data) if data is not None else bytes(int(n_bytes)))
        return address

    def mark(self) -> int:
        """The scratch allocation point, for :meth:`release`."""
        return self._scratch

    def release(self, mark: int) -> None:
        """Free the scratch allocated since :meth:`mark`."""
        self._scratch = mark

    def read(self, address: int, n_bytes: int) -> bytes:
        return bytes(self.uc.mem_read(address, n_bytes))

    def write(self, address: int, data: bytes) -> None:
        self.uc.mem_write(address, bytes(data))

    def read_u32(self, symbol: str) -> int:
        return struct.unpack("<I", self.read(self.address(symbol), 4))[0]

    def write_u32(self, symbol: str, value: int) -> None:
        self.write(self.address(symbol), struct.pack("<I", value))

    # ------------------------------------------------------------------ calls
    def call(self, function: str, *args, returns: str | None = None):
        """Call ``function(*args)`` on the target; returns (its value, :class:`Call`). An argument is a numpy
        array or ctypes structure (passed by pointer; copied into scratch and back after the call), None (NULL),
        an int (a 32-bit word), or an :class:`Arg`. ``returns``: None or a C type of :class:`Arg`."""
        buffers = []
        words: list[tuple[str, int | float]] = []
        for a in args:
            if a is None:
                words.append(("u32", 0))
            elif isinstance(a, np.ndarray):
                assert a.flags.c_contiguous
                buffers.append((a, self.alloc(a.nbytes, a.tobytes())))
                words.append(("u32", buffers[-1][1]))
            elif isinstance(a, ctypes.Structure | ctypes.Array):
                buffers.append((a, self.alloc(ctypes.sizeof(a), bytes(a))))
                words.append(("u32", buffers[-1][1]))
            elif isinstance(a, Arg):
                words.append((a.ctype, a.value))
            else:
                words.append(("u32", int(a)))
        value, cost = self._invoke(self.address(function), words, returns)
        for obj, address in buffers:
            raw = self.read(address, obj.nbytes if isinstance(obj, np.ndarray) else ctypes.sizeof(obj))
            if isinstance(obj, np.ndarray):
                obj[...] = np.frombuffer(raw, dtype=obj.dtype).reshape(obj.shape)
            else:
                ctypes.memmove(ctypes.addressof(obj), raw, len(raw))
        return value, cost

    def _invoke(self, entry: int, words, returns):
        """AAPCS: core registers r0-r3 then the stack (64-bit values in an even register pair or 8-aligned on the
        stack); with the VFP variant (hard float) float and double in s0-s15 / d0-d7 with back-filling."""
        arm = self._arm
        core: list[int] = []
        stack = bytearray()
        vfp: list[int | None] = [None] * 16  # single-precision slots s0-s15
        for ctype, value in words:
            if ctype == "f32":
                raw = struct.pack("<f", value)
            elif ctype == "f64":
                raw = struct.pack("<d", value)
            else:
                fmt = {"i32": "<i", "u32": "<I", "i64": "<q", "u64": "<Q"}[ctype]
                raw = struct.pack(fmt, int(value) & 0xFFFFFFFF if ctype == "u32" else int(value))
            halves = list(struct.unpack(f"<{len(raw) // 4}I", raw))
            if self.target.hard_float and ctype in ("f32", "f64"):
                step = len(halves)
                slot = next(k for k in range(0, 16, step) if all(v is None for v in vfp[k : k + step]))
                vfp[slot : slot + step] = halves
                continue
            if len(halves) == 2 and len(core) % 2:
                core.append(0)  # a 64-bit value starts at an even register
            if len(core) + len(halves) <= 4:
                core += halves
                continue
            core += [0] * (4 - len(core))  # no core register is used after one argument went to the stack
            while len(stack) % len(raw):
                stack += b"\0"
            stack += raw
        sp = STACK_TOP - ((len(stack) + 7) & ~7)
        uc = self.uc
        uc.mem_write(STACK_TOP - STACK_PAINT_BYTES, bytes([_PAINT]) * STACK_PAINT_BYTES)
        if stack:
            uc.mem_write(sp, bytes(stack))
        for k, v in enumerate(core):
            uc.reg_write(getattr(arm, f"UC_ARM_REG_R{k}"), v)
        for k, v in enumerate(vfp):
            if v is not None:
                uc.reg_write(getattr(arm, f"UC_ARM_REG_S{k}"), v)
        uc.reg_write(arm.UC_ARM_REG_SP, sp)
        uc.reg_write(arm.UC_ARM_REG_LR, self._return | 1)
        self._count = self._cycles = 0
        self._pending_fallthrough = None
        uc.emu_start(entry | 1, self._return)
        if self._pending_fallthrough is not None:  # the last branch went to the return trap: taken
            self._cycles += int(self._return != self._pending_fallthrough)
        painted = bytes(uc.mem_read(STACK_TOP - STACK_PAINT_BYTES, STACK_PAINT_BYTES - (STACK_TOP - sp)))
        first = next((i for i, b in enumerate(painted) if b != _PAINT), len(painted))
        stack_bytes = len(painted) - first
        cycles = self._cycles if self.models_cycles else None
        return self._return_value(returns), Call(self._count, stack_bytes, cycles)

    def _return_value(self, returns):
        arm, uc = self._arm, self.uc
        if returns is None:
            return None
        r0, r1 = uc.reg_read(arm.UC_ARM_REG_R0), uc.reg_read(arm.UC_ARM_REG_R1)
        if returns in ("f32", "f64") and self.target.hard_float:
            s0, s1 = uc.reg_read(arm.UC_ARM_REG_S0), uc.reg_read(arm.UC_ARM_REG_S1)
            if returns == "f32":
                return struct.unpack("<f", struct.pack("<I", s0))[0]
            return struct.unpack("<d", struct.pack("<II", s0, s1))[0]
        formats = {"i32": ("<I", "<i"), "u32": ("<I", "<I"), "f32": ("<I", "<f")}
        if returns in formats:
            pack, unpack = formats[returns]
            return struct.unpack(unpack, struct.pack(pack, r0))[0]
        unpack = {"i64": "<q", "u64": "<Q", "f64": "<d"}[returns]
        return struct.unpack(unpack, struct.pack("<II", r0, r1))[0]
