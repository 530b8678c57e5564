"""benchmarks.profile_registers: the loops it finds in objdump's output and the stack moves it counts."""
from benchmarks.profile_registers import vector_loops

FMA = "vfmadd231ps %zmm4,%zmm1,%zmm{}"


def _function(name: str, start: int, loop: list[str], before: list[str] = (), after: list[str] = ()) -> str:
    """objdump -d --no-show-raw-insn text of one function whose `loop` body ends in a jump back to its start."""
    lines, address = [f"{start:016x} <{name}>:"], start
    for text in before:
        lines.append(f"   {address:x}:\t{text}")
        address += 4
    top = address
    for text in loop:
        lines.append(f"   {address:x}:\t{text}")
        address += 4
    lines.append(f"   {address:x}:\tjne    {top:x} <{name}+0x{top - start:x}>")
    address += 4
    for text in after:
        lines.append(f"   {address:x}:\t{text}")
        address += 4
    return "\n".join(lines) + "\n\n"


def test_a_register_tile_loop_has_no_stack_moves_and_a_spilling_one_counts_each():
    clean = _function("tile<4, 4>", 0x1000, [FMA.format(i) for i in range(16)],
                      before=["vmovaps %zmm5,-0x78(%rsp)"], after=["vmovaps %zmm5,-0x78(%rsp)"])
    spilling = _function("tile<8, 4>", 0x2000, [FMA.format(i % 32) for i in range(32)]
                         + ["vmovaps %zmm3,0x48(%rsp)", "vmovaps 0x88(%rsp),%zmm3", "vmovups (%rdx),%zmm2"])
    assert list(vector_loops(clean + spilling)) == [("tile<4, 4>", 17, 16, 0), ("tile<8, 4>", 36, 32, 2)]


def test_loops_with_few_fmas_forward_jumps_and_plt_stubs_are_left_out():
    short = _function("scalar_loop", 0x1000, [FMA.format(i) for i in range(7)] + ["vmovaps %ymm1,(%rsp)"])
    stub = _function("tile<4, 4>@plt", 0x2000, [FMA.format(i) for i in range(16)])
    forward = ("0000000000003000 <forward>:\n   3000:\tvfmadd231ps %ymm1,%ymm2,%ymm3\n"
               "   3004:\tjmp    3010 <forward+0x10>\n\n")
    assert list(vector_loops(short + stub + forward)) == []
