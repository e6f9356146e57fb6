"""Count the instructions a Cortex-M or RISC-V image executes in its marker functions.

Usage: count_insns.py IMAGE.elf [--exact] [--core=m4|m0plus|riscv32]

Runs the ELF image in the Unicorn emulator from its reset vector (Cortex-M: the vector table
is found by cortex-m-rt's `__RESET_VECTOR` symbol; RISC-V: the ELF entry point) until it
reaches the symbol `bench_done`, and counts the instructions executed inside each marker
function: from the function's first instruction up to and including its return (to the
caller's `lr` or `ra`, with the stack pointer back at its value on entry), every callee
included. Instructions whose condition fails (in an IT block) count as executed, as on the
core. The core is a Cortex-M4 with FPU (Thumb-2) in an STM32F4's memories, with
`--core=m0plus` a Cortex-M0 (ARMv6-M, the instruction set of the RP2040's Cortex-M0+) in the
RP2040's, or with `--core=riscv32` a 32-bit RISC-V core (Unicorn's SiFive E31, RV32IMAC, for
the ESP32-C3's RV32IMC) with one RAM region of 1 MiB at 0x8000_0000 (`bench/riscv32/link.x`).
The program is `boards/stm32f4/examples/kernel_bench/program.rs`, in the STM32F4's, the
RP2040's and the RISC-V bench images (`bench/riscv32`); its markers are:

- `bench_isr`, `bench_prep`, `bench_line`: the measured calls;
- `bench_phase(phase)`: the following measured calls belong to `phase`;
- `bench_result(phase, step_events, lines)`: the phase's own counts, printed as they are;
- `bench_done`: the end; `bench_failed`: the image gave up (a panic), an error here;
- RISC-V: `_start_trap`, the trap vector: the core took an exception, an error here.

Counting is by translated block: Unicorn reports each block it executes with its start and
byte length, and the block's instructions are counted once by decoding Thumb-2 (or RISC-V
compressed and 32-bit) lengths from the image. `--exact` counts with a hook on every
instruction instead, adding on Cortex-M the instructions of IT blocks that Unicorn skips
without a hook when their condition fails (much slower; a cross-check that must give the same
figures).
The count depends only on the image: two runs give the same figures.

Output, one record a line, fields separated by spaces:

    marker PHASE NAME CALLS TOTAL MIN MAX
    result PHASE STEP_EVENTS LINES
    total INSTRUCTIONS

Exit status 0 when the image reached `bench_done`, 1 otherwise (with the reason on stderr).
"""

import struct
import sys

from unicorn import UC_ARCH_ARM, UC_HOOK_BLOCK, UC_HOOK_CODE, UC_MODE_MCLASS, UC_MODE_THUMB
from unicorn import UC_ARCH_RISCV, UC_MODE_RISCV32
from unicorn import Uc, UcError
from unicorn.arm_const import (
    UC_ARM_REG_LR,
    UC_ARM_REG_PC,
    UC_ARM_REG_R0,
    UC_ARM_REG_R1,
    UC_ARM_REG_R2,
    UC_ARM_REG_SP,
    UC_CPU_ARM_CORTEX_M0,
    UC_CPU_ARM_CORTEX_M4,
)
from unicorn.riscv_const import (
    UC_CPU_RISCV32_SIFIVE_E31,
    UC_RISCV_REG_A0,
    UC_RISCV_REG_A1,
    UC_RISCV_REG_A2,
    UC_RISCV_REG_PC,
    UC_RISCV_REG_RA,
    UC_RISCV_REG_SP,
)

MEASURED = ("bench_isr", "bench_prep", "bench_line")

# A guard against an image that never ends (the count takes under a minute, `--exact` about
# ten).
TIMEOUT_US = 60 * 60 * 1_000_000

# The STM32F4's memories (the largest of the family, so that every pin map's image fits) and
# the System Control Space, where the reset code enables the FPU (the write lands in RAM; the
# emulated core runs FPU instructions without it).
MEMORY = (
    (0x0800_0000, 2 << 20),  # flash
    (0x1000_0000, 64 << 10),  # core-coupled RAM
    (0x2000_0000, 192 << 10),  # SRAM
    (0xE000_E000, 4 << 10),  # System Control Space
)

# The RP2040's: the QSPI flash as execute-in-place maps it, the SRAM banks (striped and the
# two 4 KiB ones), the System Control Space.
MEMORY_RP2040 = (
    (0x1000_0000, 2 << 20),  # flash (XIP)
    (0x2000_0000, 264 << 10),  # SRAM
    (0xE000_E000, 4 << 10),  # System Control Space
)

# The RISC-V bench image's one RAM region (`bench/riscv32/link.x`): code, data and stack.
MEMORY_RISCV32 = ((0x8000_0000, 1 << 20),)


class Arch:
    """An instruction set's registers and instruction lengths, and how its images start."""

    def __init__(self, arch, mode, pc, sp, ret, args, thumb):
        self.arch, self.mode = arch, mode
        self.pc, self.sp, self.ret, self.args = pc, sp, ret, args
        self.thumb = thumb  # Thumb-2 lengths and IT blocks; otherwise RISC-V lengths


ARM = Arch(
    UC_ARCH_ARM,
    UC_MODE_THUMB | UC_MODE_MCLASS,
    UC_ARM_REG_PC,
    UC_ARM_REG_SP,
    UC_ARM_REG_LR,
    (UC_ARM_REG_R0, UC_ARM_REG_R1, UC_ARM_REG_R2),
    thumb=True,
)

RISCV32 = Arch(
    UC_ARCH_RISCV,
    UC_MODE_RISCV32,
    UC_RISCV_REG_PC,
    UC_RISCV_REG_SP,
    UC_RISCV_REG_RA,
    (UC_RISCV_REG_A0, UC_RISCV_REG_A1, UC_RISCV_REG_A2),
    thumb=False,
)

# --core: the instruction set, Unicorn's CPU model and the memories.
CORES = {
    "m4": (ARM, UC_CPU_ARM_CORTEX_M4, MEMORY),
    "m0plus": (ARM, UC_CPU_ARM_CORTEX_M0, MEMORY_RP2040),
    "riscv32": (RISCV32, UC_CPU_RISCV32_SIFIVE_E31, MEMORY_RISCV32),
}


def fail(message):
    print(f"count_insns: {message}", file=sys.stderr)
    sys.exit(1)


def read_elf(data):
    """The entry point, the loadable segments (load address, bytes) and the symbol table
    (name -> address)."""
    if data[:4] != b"\x7fELF" or data[4] != 1 or data[5] != 1:
        fail("not a 32-bit little-endian ELF file")
    (entry,) = struct.unpack_from("<I", data, 0x18)
    (phoff, shoff) = struct.unpack_from("<II", data, 0x1C)
    (phentsize, phnum, shentsize, shnum) = struct.unpack_from("<HHHH", data, 0x2A)
    segments = []
    for i in range(phnum):
        (p_type, offset, _vaddr, paddr, filesz) = struct.unpack_from(
            "<5I", data, phoff + i * phentsize
        )
        if p_type == 1 and filesz > 0:  # PT_LOAD, at its load (physical) address
            segments.append((paddr, data[offset : offset + filesz]))
    sections = [
        struct.unpack_from("<10I", data, shoff + i * shentsize) for i in range(shnum)
    ]
    symbols = {}
    for sh in sections:
        if sh[1] != 2:  # SHT_SYMTAB
            continue
        strtab = sections[sh[6]]  # sh_link
        str_off = strtab[4]
        for k in range(sh[5] // 16):
            (name, value, _size, _info) = struct.unpack_from(
                "<IIIB", data, sh[4] + 16 * k
            )
            end = data.index(b"\0", str_off + name)
            symbols[data[str_off + name : end].decode("utf-8", "replace")] = value
    return entry, segments, symbols


class Counter:
    """Per (phase, marker): calls, total, min and max instructions; the phases' results."""

    def __init__(self, uc, arch, symbols):
        self.uc = uc
        self.arch = arch
        need = MEASURED + ("bench_phase", "bench_result", "bench_done", "bench_failed")
        missing = [n for n in need if n not in symbols]
        if missing:
            fail("symbols missing from the image: " + ", ".join(missing))
        self.addr = {n: symbols[n] & ~1 for n in need}
        self.measured = {self.addr[n]: n for n in MEASURED}
        self.phase_at = self.addr["bench_phase"]
        self.result_at = self.addr["bench_result"]
        self.failed_at = self.addr["bench_failed"]
        self.lengths = {}
        self.it_pending = []  # addresses of the current IT block's instructions not yet run
        self.phase = 0
        self.active = None  # (name, return address, stack pointer at entry)
        self.current = 0
        self.stats = {}
        self.results = []
        self.total = 0
        self.failed = None
        self.faults = set()

    def block_length(self, address, size):
        """Instructions in the block at `address` of `size` bytes."""
        key = (address, size)
        n = self.lengths.get(key)
        if n is None:
            n, at = 0, address
            while at < address + size:
                at += self.length_at(at)
                n += 1
            self.lengths[key] = n
        return n

    def on_block(self, uc, address, size, _data):
        self.at(address, self.block_length(address, size))

    def on_instruction(self, uc, address, size, _data):
        # Unicorn calls no hook for an instruction of an IT block whose condition fails: count
        # those once execution has passed them, where they were.
        if self.it_pending:
            if address in self.it_pending:
                self.it_pending.remove(address)
            else:
                skipped = len(self.it_pending)
                self.it_pending = []
                if self.active is not None:
                    self.current += skipped
                self.total += skipped
        self.at(address, 1)
        if self.arch.thumb and size == 2:
            first, second = self.uc.mem_read(address, 2)
            if second == 0xBF and first & 0x0F:  # IT (a zero mask is a hint such as NOP)
                mask = first & 0x0F
                at = address + 2
                for _ in range(5 - (mask & -mask).bit_length()):
                    self.it_pending.append(at)
                    at += self.length_at(at)

    def length_at(self, address):
        """Bytes of the Thumb-2 or RISC-V instruction at `address`."""
        if not self.arch.thumb:
            # RISC-V: 32-bit when the low two bits are 11, compressed (16-bit) otherwise.
            return 4 if self.uc.mem_read(address, 1)[0] & 0b11 == 0b11 else 2
        half = self.uc.mem_read(address + 1, 1)[0]
        return 4 if (half >> 3) in (0b11101, 0b11110, 0b11111) else 2

    def at(self, address, n):
        """Execution reaches `address` and runs `n` instructions from there."""
        if self.active is not None:
            (name, ret, sp) = self.active
            if address == ret and self.uc.reg_read(self.arch.sp) == sp:
                self.close(name)
        if address in self.measured and self.active is None:
            ret = self.uc.reg_read(self.arch.ret) & ~1
            self.active = (self.measured[address], ret, self.uc.reg_read(self.arch.sp))
            self.current = 0
        elif address == self.phase_at:
            self.phase = self.uc.reg_read(self.arch.args[0])
        elif address == self.result_at:
            r = [self.uc.reg_read(x) for x in self.arch.args]
            self.results.append(r)
        elif address == self.failed_at:
            self.failed = "the image reached bench_failed (a panic, or a refused set-up)"
            self.uc.emu_stop()
        elif address in self.faults:
            self.failed = f"the core took an exception (handler at {address:#010x})"
            self.uc.emu_stop()
        if self.active is not None:
            self.current += n
        self.total += n

    def close(self, name):
        key = (self.phase, name)
        calls, total, lo, hi = self.stats.get(key, (0, 0, None, 0))
        c = self.current
        self.stats[key] = (calls + 1, total + c, c if lo is None else min(lo, c), max(hi, c))
        self.active = None


def main(argv):
    args = [a for a in argv[1:] if not a.startswith("--")]
    exact = "--exact" in argv[1:]
    cores = [a.removeprefix("--core=") for a in argv[1:] if a.startswith("--core=")]
    core = cores[-1] if cores else "m4"
    if len(args) != 1 or core not in CORES:
        fail("usage: count_insns.py IMAGE.elf [--exact] [--core=m4|m0plus|riscv32]")
    arch, cpu, memory = CORES[core]
    with open(args[0], "rb") as f:
        entry, segments, symbols = read_elf(f.read())

    uc = Uc(arch.arch, arch.mode)
    uc.ctl_set_cpu_model(cpu)
    for base, size in memory:
        uc.mem_map(base, size)
    for address, data in segments:
        uc.mem_write(address, data)
    counter = Counter(uc, arch, symbols)
    if arch.thumb:
        if "__RESET_VECTOR" not in symbols:
            fail("symbol missing from the image: __RESET_VECTOR")
        table = symbols["__RESET_VECTOR"] - 4
        # The vector table: initial stack pointer, reset vector.
        sp, reset = struct.unpack("<II", uc.mem_read(table, 8))
        uc.reg_write(UC_ARM_REG_SP, sp)
        start = reset | 1
        # The core's exception handlers (NMI, HardFault, MemManage, BusFault, UsageFault, …):
        # the image has no interrupt sources here, so reaching one is a fault (an FPU
        # instruction the emulated core refused, a bad access) and ends the count.
        vectors = struct.unpack("<14I", uc.mem_read(table + 8, 56))
        counter.faults = {v & ~1 for v in vectors if v & 1}
    else:
        # The image's start-up sets the stack pointer and the trap vector itself; every trap
        # goes to `_start_trap`, and the image enables no interrupt: reaching it is a fault.
        if "_start_trap" not in symbols:
            fail("symbol missing from the image: _start_trap")
        start = entry
        counter.faults = {symbols["_start_trap"]}
    if exact:
        uc.hook_add(UC_HOOK_CODE, counter.on_instruction)
    else:
        uc.hook_add(UC_HOOK_BLOCK, counter.on_block)
    try:
        uc.emu_start(start, counter.addr["bench_done"], timeout=TIMEOUT_US)
    except UcError as e:
        fail(f"emulation stopped at {uc.reg_read(arch.pc):#010x}: {e}")
    if counter.failed:
        fail(counter.failed)
    if uc.reg_read(arch.pc) != counter.addr["bench_done"]:
        pc = uc.reg_read(arch.pc)
        fail(f"emulation ended at {pc:#010x}, not at bench_done (time limit reached?)")

    for (phase, name), (calls, total, lo, hi) in sorted(counter.stats.items()):
        print(f"marker {phase} {name} {calls} {total} {lo} {hi}")
    for phase, steps, lines in counter.results:
        print(f"result {phase} {steps} {lines}")
    print(f"total {counter.total}")


if __name__ == "__main__":
    main(sys.argv)
