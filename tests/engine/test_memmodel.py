"""Memory model: closed-form cache behaviour (scans, LRU thrash, random reads), coalescing, presets."""
import numba
import numpy as np
import pytest

from layerbvh import memmodel as mm
from layerbvh.memmodel import CacheLevel, Caches, Preset


# Not cached: numba's cache of a caller does not notice changes to the functions it calls, so a
# cached replay would keep testing an old cache_access.
@numba.njit
def _replay(tags, stamps, dirty, params, counts, clock, units, addrs, writes, held):
    for i in range(addrs.shape[0]):
        held[i] = mm.cache_access(tags, stamps, dirty, params, counts, clock, units[i], addrs[i], writes[i])


def replay(caches: Caches, addrs, unit=0, write=False) -> np.ndarray:
    """Feeds addrs (all from `unit`, or one unit per address; loads, or stores where `write`)
    through the hierarchy; returns the level that held each."""
    addrs = np.ascontiguousarray(addrs, dtype=np.int64)
    units = np.broadcast_to(np.asarray(unit, dtype=np.int64), addrs.shape).copy()
    writes = np.broadcast_to(np.asarray(write, dtype=np.bool_), addrs.shape).copy()
    held = np.empty(len(addrs), dtype=np.int64)
    _replay(*caches.arrays, units, addrs, writes, held)
    return held


def hierarchy(*levels: CacheLevel, units: int = 1) -> Caches:
    return Caches(Preset(name="test", description="test hierarchy", kind="cpu", units=units,
                         resident_warps=1, block_warps=1, warp=1,
                         segment_bytes=levels[0].line_bytes, levels=levels,
                         flush_private_each_kernel=False, source="test"))


def hits_misses(caches: Caches, level: int) -> tuple[int, int]:
    hits, misses = caches.counts[level, :2]
    return int(hits), int(misses)


# --- single level, closed forms -----------------------------------------------------------------

@pytest.mark.parametrize("line", [32, 48, 64, 128])
def test_sequential_scan_misses_once_per_line(line):
    # 4-byte elements over 1.5 MiB (48 x a 32 KiB cache): each line misses on its first word and
    # hits on the other line/4 - 1, so the hit rate is exactly 1 - 4/line (0.9375 for 64 B).
    # 48-byte lines exercise the non-power-of-two division path.
    c = hierarchy(CacheLevel("L1", 32 * 1024 // 64 * line, 8, line, shared=False))
    region = 48 * 32 * 1024 // 64 * line
    held = replay(c, np.arange(0, region, 4))
    assert hits_misses(c, 0) == (region // 4 - region // line, region // line)
    assert c.hit_rates() == [1 - 4 / line]
    assert (held[:: line // 4] == 1).all() and (np.delete(held, np.s_[:: line // 4]) == 0).all()
    assert c.bytes_below() == [region]


@pytest.mark.parametrize("sets", [64, 12])  # 12: non-power-of-two set count (unsigned modulo path)
def test_cyclic_set_conflict_of_ways_plus_one_lines_always_misses(sets):
    # ways + 1 lines at a stride of sets * line (the cache's size: all in set 0), read cyclically:
    # LRU always evicts the line needed next, so every one of the passes * (ways + 1) reads
    # misses, the first pass included.
    ways, line, passes = 4, 64, 10
    c = hierarchy(CacheLevel("L1", sets * ways * line, ways, line, shared=False))
    working = np.arange(ways + 1) * sets * line
    held = replay(c, np.tile(working, passes))
    assert hits_misses(c, 0) == (0, passes * (ways + 1))
    assert (held == 1).all()


@pytest.mark.parametrize("sets", [64, 12])
def test_cyclic_scan_that_fits_hits_after_first_pass(sets):
    # The whole capacity (sets * ways lines), one read per line, k passes: the first pass fills
    # the cache exactly, every later read hits: hit rate (k - 1) / k.
    ways, line, passes = 4, 64, 7
    c = hierarchy(CacheLevel("L1", sets * ways * line, ways, line, shared=False))
    working = np.arange(sets * ways) * line
    held = replay(c, np.tile(working, passes))
    assert hits_misses(c, 0) == ((passes - 1) * sets * ways, sets * ways)
    assert c.hit_rates() == [(passes - 1) / passes]
    assert (held[: sets * ways] == 1).all() and (held[sets * ways:] == 0).all()
    # ways lines in one set (the conflict case above minus one line) also fit.
    c.reset()
    replay(c, np.tile(np.arange(ways) * sets * line, passes))
    assert hits_misses(c, 0) == ((passes - 1) * ways, ways)


def test_replacement_is_lru_not_fifo():
    # 2-way, one set: A B A C. LRU evicts B (A was used since), FIFO would evict A.
    c = hierarchy(CacheLevel("L1", 2 * 64, 2, 64, shared=False))
    a, b, cc = 0, 64, 128
    assert list(replay(c, [a, b, a, cc])) == [1, 1, 0, 1]
    assert list(replay(c, [a, b])) == [0, 1]


@pytest.mark.parametrize("ratio", [4, 2])
def test_uniform_random_reads_hit_at_capacity_over_footprint(ratio):
    # Uniform random reads over N lines through an LRU cache of C lines: in steady state the
    # cache holds C distinct lines and every line is equally likely to be among them (per set:
    # ways of N / sets), so each read hits with probability C / N. Counted after a warm-up that
    # fills the cache; tolerance 5 binomial standard deviations over 2M reads.
    line, ways, sets = 64, 4, 64
    capacity = ways * sets
    footprint = ratio * capacity
    c = hierarchy(CacheLevel("L1", capacity * line, ways, line, shared=False))
    rng = np.random.default_rng(12345)
    replay(c, rng.integers(0, footprint, 20 * footprint) * line)
    c.counts[:] = 0
    reads = 2_000_000
    replay(c, rng.integers(0, footprint, reads) * line + rng.integers(0, line, reads))
    p = capacity / footprint
    sigma = (p * (1 - p) / reads) ** 0.5
    assert abs(c.hit_rates()[0] - p) < 5 * sigma


# --- two levels, units ----------------------------------------------------------------------------

def test_working_set_between_l1_and_l2():
    # 256 lines (16 KiB) read cyclically, one read per line, 5 passes. L1 (64 lines, 16 sets x
    # 4 ways) sees 16 lines cycling through each set: LRU thrash, no hit. L2 (1024 lines) holds
    # them all: misses in the first pass only, hit rate 4/5. Bytes: every read refills L1 from
    # L2 (5 x 256 x 64 B), L2 fetches each line from DRAM once.
    line, lines, passes = 64, 256, 5
    c = hierarchy(CacheLevel("L1", 4 * 1024, 4, line, shared=False),
                  CacheLevel("L2", 64 * 1024, 8, line, shared=True))
    held = replay(c, np.tile(np.arange(lines) * line, passes))
    assert hits_misses(c, 0) == (0, passes * lines)
    assert hits_misses(c, 1) == ((passes - 1) * lines, lines)
    assert int(c.counts[2, mm.C_HITS]) == lines  # DRAM accesses
    assert c.hit_rates() == [0.0, (passes - 1) / passes]
    assert c.bytes_below() == [passes * lines * line, lines * line]
    assert (held[:lines] == 2).all() and (held[lines:] == 1).all()


def test_levels_with_their_own_line_sizes():
    # L1 with 32-byte lines under an L2 with 128-byte lines: reading a 128-byte block word by
    # word misses L1 four times (once per 32 B line) and L2 once.
    c = hierarchy(CacheLevel("L1", 4 * 1024, 4, 32, shared=False),
                  CacheLevel("L2", 64 * 1024, 8, 128, shared=True))
    held = replay(c, np.arange(0, 128, 4))
    assert hits_misses(c, 0) == (28, 4)
    assert hits_misses(c, 1) == (3, 1)
    assert list(held[::8]) == [2, 1, 1, 1]
    assert c.bytes_below() == [4 * 32, 128]


def two_units() -> Caches:
    return hierarchy(CacheLevel("L1", 4 * 1024, 4, 64, shared=False),
                     CacheLevel("L2", 64 * 1024, 8, 64, shared=True), units=2)


def test_private_levels_are_per_unit_shared_levels_are_not():
    c = two_units()
    lines = np.arange(32) * 64  # fit both levels
    assert (replay(c, lines, unit=0) == 2).all()
    # The second unit's own L1 has never seen them; the shared L2 has.
    assert (replay(c, lines, unit=1) == 1).all()
    assert hits_misses(c, 0) == (0, 64)
    assert hits_misses(c, 1) == (32, 32)
    # Both L1s now hold them.
    assert (replay(c, lines, unit=0) == 0).all()
    assert (replay(c, lines, unit=1) == 0).all()


def test_flush_private_empties_l1_keeps_l2():
    c = two_units()
    lines = np.arange(32) * 64
    replay(c, lines, unit=0)
    assert (replay(c, lines, unit=0) == 0).all()
    c.flush_private()
    assert (replay(c, lines, unit=0) == 1).all()  # L1 misses again, L2 still hits
    assert (replay(c, lines, unit=0) == 0).all()  # and L1 is refilled
    c.reset()
    assert (replay(c, lines, unit=0) == 2).all()
    assert hits_misses(c, 0) == (0, 32)


def test_invalid_access_returns_minus_one_and_counts_nothing():
    c = two_units()
    before = c.counts.copy()
    assert list(replay(c, [-64, 0, 0], unit=np.array([0, 2, -1]))) == [-1, -1, -1]
    assert (c.counts == before).all()
    assert (c.arrays[0] == mm.EMPTY_TAG).all()


# --- stores: write-allocate, write-back ----------------------------------------------------------

def test_a_store_allocates_its_line_and_a_dirty_victim_is_written_back_once():
    # One set of 2 ways: store A (a write miss: the line is fetched), load B, load C evicts A (the
    # least recently used, dirty): one write-back, into DRAM (no level below). Load A again evicts
    # B, which is clean: nothing written. Then a store that hits (A) misses nothing.
    c = hierarchy(CacheLevel("L1", 2 * 64, 2, 64, shared=False))
    a, b, cc = 0, 64, 128
    assert list(replay(c, [a], write=True)) == [1]
    assert list(replay(c, [b, cc, a])) == [1, 1, 1]
    assert list(replay(c, [a + 8], write=True)) == [0]
    counts = c.counts
    assert (counts[0, mm.C_MISSES], counts[0, mm.C_WRITE_MISSES], counts[0, mm.C_WRITE_BACKS]) == (4, 1, 1)
    assert counts[1, mm.C_WRITE_BACKS] == 1 and c.dram_write_bytes() == 64
    assert c.bytes_written_below() == [64]


@pytest.mark.parametrize("write", [True, False])
def test_a_store_stream_writes_back_every_line_the_caches_cannot_hold(write):
    # N lines stored word by word (16 stores a line), through L1 (C1 lines) over L2 (C2 > C1):
    # each line misses once in L1 and once in L2 (write misses: the stores fetch their lines);
    # L1 evicts N - C1 dirty lines, each still held by L2 (C1 lines after its fill, where L2
    # keeps C2), which marks it dirty; L2 then evicts N - C2 lines, all dirty: N - C2 lines
    # reach DRAM. The same stream loaded writes nothing back (the control).
    line, n = 64, 4096
    c1, c2 = 64, 1024
    c = hierarchy(CacheLevel("L1", c1 * line, 4, line, shared=False),
                  CacheLevel("L2", c2 * line, 8, line, shared=True))
    replay(c, np.arange(0, n * line, 4), write=write)
    counts = c.counts
    assert hits_misses(c, 0) == (15 * n, n) and hits_misses(c, 1) == (0, n)
    stores = n if write else 0
    assert list(counts[:2, mm.C_WRITE_MISSES]) == [stores, stores]
    assert list(counts[:, mm.C_WRITE_BACKS]) == ([n - c1, n - c2, n - c2] if write else [0, 0, 0])
    assert c.dram_write_bytes() == (n - c2) * line * write


def test_a_flush_writes_the_private_dirty_lines_back_to_the_shared_level():
    # A GPU's L1s at a kernel's end: unit 1 stores 32 lines (its L1 holds them, dirty), the flush
    # writes all 32 back into L2, which holds them (dirty there, nothing reaches DRAM) and empties
    # the L1; flushing again writes nothing.
    c = two_units()
    replay(c, np.arange(32) * 64, unit=1, write=True)
    c.flush_private()
    c.flush_private()
    tags, _, dirty, params, counts, _ = c.arrays
    l2 = slice(params[1, mm.P_OFFSET], None)
    assert list(counts[:, mm.C_WRITE_BACKS]) == [32, 0, 0]
    assert int(dirty[l2].sum()) == 32 and (tags[:params[1, mm.P_OFFSET]] == mm.EMPTY_TAG).all()
    assert (replay(c, np.arange(32) * 64, unit=1) == 1).all()  # L1 refills from L2


# --- coalescing ----------------------------------------------------------------------------------

def segments(addrs, size, seg=32, active=None):
    addrs = np.asarray(addrs, dtype=np.int64)
    active = np.ones(len(addrs), dtype=np.bool_) if active is None else np.asarray(active)
    out = np.full(len(addrs) * (size // seg + 2), -7, dtype=np.int64)
    n = mm.coalesce(addrs, active, len(addrs), size, seg, out)
    return list(out[:n])


def test_coalesce_consecutive_words_of_a_warp():
    # 32 lanes x 4 consecutive bytes from a 128-byte boundary: 128 bytes = four 32-byte sectors.
    assert segments(1280 + 4 * np.arange(32), 4) == [40, 41, 42, 43]
    # Reversed lanes touch the same sectors.
    assert segments(1280 + 4 * np.arange(32)[::-1], 4) == [40, 41, 42, 43]


def test_coalesce_broadcast_is_one_segment():
    assert segments(np.full(32, 1000), 4) == [31]


def test_coalesce_records_spanning_sectors():
    # 64-byte records at stride 64, aligned: two 32-byte sectors each, none shared.
    assert segments(64 * np.arange(32), 64) == list(range(64))
    # One unaligned 64-byte record (bytes 16..79) touches three sectors.
    assert segments([16], 64) == [0, 1, 2]
    # With 64-byte segments (CPU lines) the aligned records take one each.
    assert segments(64 * np.arange(16), 64, seg=64) == list(range(16))


def test_coalesce_skips_inactive_lanes_and_negative_addresses():
    assert segments([0, 4096, -4, 8192], 4, active=[True, False, True, True]) == [0, 256]
    assert segments([-1, -64], 4) == []
    assert segments([0, 4096], 4, active=[False, False]) == []
    # Only the first n lanes count.
    out = np.zeros(8, dtype=np.int64)
    assert mm.coalesce(np.array([0, 4096], dtype=np.int64), np.ones(2, np.bool_), 1, 4, 32, out) == 1


# --- presets -------------------------------------------------------------------------------------

def test_unknown_preset_names_the_valid_ones():
    with pytest.raises(ValueError, match="unknown preset 'nope'") as info:
        mm.preset("nope")
    for name in ("gtx965m", "h200", "cpu"):
        assert name in str(info.value)


@pytest.mark.parametrize("name", sorted(mm.PRESETS))
def test_presets_describe_their_levels_and_build(name):
    p = mm.preset(name)
    line = p.describe()
    assert "\n" not in line and p.description in line
    for level in p.levels:
        assert f"{level.name} {mm.format_bytes(level.size_bytes)}" in line
    d = p.as_dict()
    assert set(d) == set(Preset.__dataclass_fields__)
    assert [lv["size_bytes"] for lv in d["levels"]] == [lv.size_bytes for lv in p.levels]
    assert p.source
    c = Caches(p)
    tags, stamps, dirty, params, counts, clock = c.arrays
    assert params.shape == (len(p.levels), 6) and counts.shape == (len(p.levels) + 1, mm.COUNT_COLUMNS)
    assert len(tags) == len(stamps) == len(dirty) == sum(
        (1 if lv.shared else p.units) * lv.size_bytes // lv.line_bytes for lv in p.levels)


def test_gpu_presets_numbers():
    g = mm.preset("gtx965m")
    assert (g.units, g.warp, g.segment_bytes, g.resident_warps, g.block_warps) == (8, 32, 32, 16, 4)
    assert [(lv.size_bytes, lv.line_bytes, lv.shared) for lv in g.levels] == [
        (24 * 1024, 32, False), (1024 * 1024, 32, True)]
    h = mm.preset("h200")
    assert h.units == 132 and h.flush_private_each_kernel
    assert [(lv.size_bytes, lv.shared) for lv in h.levels] == [(256 * 1024, False), (60 * 1024 ** 2, True)]


def test_host_cpu_preset_on_this_machine():
    p = mm.host_cpu_preset()
    assert p is not mm.PRESETS["cpu"] and p == mm.PRESETS["cpu"]
    assert p.kind == "cpu" and p.resident_warps == 1 and not p.flush_private_each_kernel
    assert len(p.levels) >= 2 and p.levels[-1].shared and not p.levels[0].shared
    assert p.warp in (4, 8, 16) and p.block_warps == mm.DRJIT_LLVM_BLOCK_LANES // p.warp


def _fake_sys(root, caches):
    for i, (level, kind, size, ways, line, cpus) in enumerate(caches):
        d = root / f"index{i}"
        d.mkdir(parents=True)
        for name, value in (("level", level), ("type", kind), ("size", size),
                            ("ways_of_associativity", ways), ("coherency_line_size", line),
                            ("shared_cpu_list", cpus)):
            (d / name).write_text(f"{value}\n")


def test_host_cpu_preset_reads_sys_and_cpuinfo(tmp_path):
    _fake_sys(tmp_path / "cache", [
        (1, "Data", "48K", 12, 64, "0"),
        (1, "Instruction", "32K", 8, 64, "0"),
        (2, "Unified", "2048K", 16, 64, "0,64"),
        (3, "Unified", "96M", 0, 64, "0-7,64-71"),
    ])
    (tmp_path / "cpuinfo").write_text("processor\t: 0\nmodel name\t: Test CPU 9000\n"
                                      "flags\t\t: fpu sse2 avx avx2 fma\n")
    p = mm.host_cpu_preset(cache_dir=tmp_path / "cache", cpuinfo=tmp_path / "cpuinfo", units=4)
    assert [(lv.name, lv.size_bytes, lv.ways, lv.line_bytes, lv.shared) for lv in p.levels] == [
        ("L1", 48 * 1024, 12, 64, False),
        ("L2", 2 * 1024 ** 2, 16, 64, True),
        ("L3", 96 * 1024 ** 2, 96 * 1024 ** 2 // 64, 64, True),  # ways 0: fully associative
    ]
    assert (p.units, p.warp, p.block_warps, p.segment_bytes) == (4, 8, 2048, 64)
    assert "Test CPU 9000" in p.description and "cache" in p.source


def test_host_cpu_preset_fallback_without_sys(tmp_path):
    p = mm.host_cpu_preset(cache_dir=tmp_path / "missing", cpuinfo=tmp_path / "missing", units=2)
    assert "FALLBACK" in p.source
    assert [lv.size_bytes for lv in p.levels] == [spec[1] for spec in mm.FALLBACK_CPU_LEVELS]
    assert p.warp == 4 and p.description.startswith("this host: unknown CPU")


def test_level_size_must_be_whole_sets():
    with pytest.raises(ValueError, match="whole number of sets"):
        CacheLevel("L1", 1000, 4, 64, shared=False)
    with pytest.raises(ValueError, match="positive"):
        CacheLevel("L1", 1024, 0, 64, shared=False)
    assert CacheLevel("L1", 3 * 1024, 4, 64, shared=False).sets == 12


def test_private_levels_must_come_first():
    with pytest.raises(ValueError, match="private levels must come before shared"):
        hierarchy(CacheLevel("L1", 4096, 4, 64, shared=True), CacheLevel("L2", 65536, 8, 64, shared=False))


def test_with_segment_makes_one_transaction_one_line():
    """128-byte transactions (a GPU's whole lines instead of its 32-byte sectors): every level
    allocates 128-byte lines, a 64-byte record at a 128-byte boundary is one transaction, and the
    preset keeps its name apart; a size that is no power of two is refused."""
    from layerbvh.memmodel import with_segment
    p = with_segment(mm.preset("gtx965m"), 128)
    assert p.name == "gtx965m-s128" and p.segment_bytes == 128
    assert all(level.line_bytes == 128 for level in p.levels)
    assert with_segment(mm.preset("gtx965m"), 32) is mm.preset("gtx965m")
    out = np.empty(8, np.int64)
    assert mm.coalesce(np.array([256, 320], np.int64), np.ones(2, np.bool_), 2, 64, 128, out) == 1
    with pytest.raises(ValueError, match="power of two"):
        with_segment(mm.preset("h200"), 48)
