"""The numba cache at start: a read-only one is copied (numba would ignore it), and a start says when it compiles."""

from __future__ import annotations

import importlib
import logging
import os
import sys

import numba.core.config
import pytest

from service.ops import kernel_cache

KERNEL = '''
import numba


@numba.njit(cache=True)
def twice_plus_one(x):
    return 2 * x + 1
'''


def test_a_writable_cache_is_used_as_it_is(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert kernel_cache.writable(str(tmp_path))
    assert kernel_cache.usable_cache_dir() == str(tmp_path) == os.environ["NUMBA_CACHE_DIR"]


def test_no_directory_leaves_numbas_default(monkeypatch):
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    assert kernel_cache.usable_cache_dir() is None and "NUMBA_CACHE_DIR" not in os.environ


def test_a_path_that_cannot_be_written_is_not_writable(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert not kernel_cache.writable(str(blocker / "cache"))


def test_a_read_only_cache_is_copied_and_numba_pointed_at_the_copy(tmp_path, monkeypatch):
    image = tmp_path / "image-cache"
    (image / "core_abc").mkdir(parents=True)
    (image / "core_abc" / "kernel.nbi").write_bytes(b"index")
    (image / "core_abc" / "kernel.1.nbc").write_bytes(b"code")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(image))
    monkeypatch.setattr(numba.core.config, "CACHE_DIR", str(image))
    monkeypatch.setattr(kernel_cache, "writable", lambda directory: directory != str(image))
    monkeypatch.setattr(kernel_cache.tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    copy = kernel_cache.usable_cache_dir()
    assert copy != str(image) and os.environ["NUMBA_CACHE_DIR"] == copy == numba.core.config.CACHE_DIR
    assert copy.startswith(str(tmp_path / "tmp"))
    copied = tmp_path / "tmp" / copy / "core_abc"
    assert sorted(p.name for p in copied.iterdir()) == ["kernel.1.nbc", "kernel.nbi"]
    # the next start (a restarted container keeps its /tmp) reuses the copy, keeping what was added to it
    (copied / "kernel.nbi").write_bytes(b"index with more entries")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(image))
    assert kernel_cache.usable_cache_dir() == copy
    assert (copied / "kernel.nbi").read_bytes() == b"index with more entries"


@pytest.fixture
def kernel_module(tmp_path, monkeypatch):
    """A module with one cached kernel, its cache in a directory of its own."""
    monkeypatch.setattr(numba.core.config, "CACHE_DIR", str(tmp_path / "cache"))
    (tmp_path / "kernelpkg_for_cache_test").mkdir()
    (tmp_path / "kernelpkg_for_cache_test" / "__init__.py").write_text("")
    (tmp_path / "kernelpkg_for_cache_test" / "kernels.py").write_text(KERNEL)
    monkeypatch.syspath_prepend(str(tmp_path))

    def load():
        for name in [n for n in sys.modules if n.startswith("kernelpkg_for_cache_test")]:
            del sys.modules[name]
        return importlib.import_module("kernelpkg_for_cache_test.kernels")

    yield load
    for name in [n for n in sys.modules if n.startswith("kernelpkg_for_cache_test")]:
        del sys.modules[name]


def test_a_start_says_when_it_compiles_and_when_it_loads(kernel_module, caplog):
    caplog.set_level(logging.INFO, logger="passive_locator")
    module = kernel_module()
    assert not kernel_cache.has_code_for_this_cpu(module.twice_plus_one)
    kernel_cache.load_kernels(lambda: module.twice_plus_one(3), packages=("kernelpkg_for_cache_test.",))
    first = [r.getMessage() for r in caplog.records]
    assert first[0].startswith("compiling kernels: 1 of the 1 imported so far have no code for this CPU")
    assert "kernels ready in" in first[1] and ": 1 compiled, 0 loaded" in first[1]

    caplog.clear()
    module = kernel_module()  # a new process's view: the same source, the cache now filled
    assert kernel_cache.has_code_for_this_cpu(module.twice_plus_one)
    kernel_cache.load_kernels(lambda: module.twice_plus_one(3), packages=("kernelpkg_for_cache_test.",))
    second = [r.getMessage() for r in caplog.records]
    assert second[0].startswith("loading 1 kernels from the numba cache")
    assert ": 0 compiled, 1 loaded" in second[1]
