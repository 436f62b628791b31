"""gpupro.runtime: glibc's malloc keeps freed memory unless the environment says not to."""

import os
import platform

from gpupro import runtime


def test_freed_memory_is_kept_on_glibc_unless_turned_off():
    expected = platform.libc_ver()[0] == "glibc" and os.environ.get("GPUPRO_KEEP_FREED_MEMORY", "1") != "0"
    assert runtime.KEPT_FREED_MEMORY == expected


def test_the_environment_can_leave_malloc_alone(monkeypatch):
    monkeypatch.setenv("GPUPRO_KEEP_FREED_MEMORY", "0")
    assert runtime.keep_freed_memory() is False
