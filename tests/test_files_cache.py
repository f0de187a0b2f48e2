"""One user cache directory (hostlink/files/cache.py) for every cache: the catalogue and solver databases, the C
firmware core's host build and its Cortex-M builds all live below ``$XDG_CACHE_HOME/startracker-companion``."""

from pathlib import Path

from hostlink.files.cache import cache_dir
from hostlink.portkit import cortexm, firmware_c
from hostlink.sky import catalogue


def test_every_cache_follows_xdg_cache_home(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    root = tmp_path / "startracker-companion"
    assert cache_dir() == root
    assert catalogue.cache_dir() == root
    assert firmware_c._cache_root().parent == root
    assert cortexm._cache_root().parent == root


def test_without_xdg_cache_home_it_is_under_the_home_directory(tmp_path, monkeypatch):
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    assert cache_dir() == Path(tmp_path) / ".cache" / "startracker-companion"
