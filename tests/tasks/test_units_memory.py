"""Each unit starts with the memory earlier units freed given back to the OS (tasks.units.release_free_memory),
so a long-lived worker's RSS under a unit is that unit's own, not the high-water mark of what came before."""

import platform
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc malloc_trim")
def test_freed_heap_goes_back_before_a_unit():
    code = textwrap.dedent("""
        def rss():
            for line in open("/proc/self/status"):
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
        from tasks.units import release_free_memory
        a = [bytes(2000) + bytes([i % 256]) for i in range(100_000)]  # ~200 MB of malloc'd chunks
        tail = a[-1]  # the heap top stays in use: free() alone cannot shrink the heap
        held = rss(); del a; freed = rss(); release_free_memory(); after = rss()
        print(held, freed, after)
    """)
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    held, freed, after = map(float, out.stdout.split())
    assert freed > held - 50  # glibc keeps the freed chunks in the process
    assert after < freed - 150  # ... until the unit starts and gives them back
