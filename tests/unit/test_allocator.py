"""The C allocator setting a run starts with (``occtrain.allocator``)."""

from __future__ import annotations

import platform

import pytest

from occtrain.allocator import ENV, keep_freed_memory


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_glibc_keeps_freed_memory():
    assert keep_freed_memory() is True


def test_the_system_allocator_on_request(monkeypatch):
    monkeypatch.setenv(ENV, "system")
    assert keep_freed_memory() is False
