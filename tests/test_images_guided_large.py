"""Large frames (docs/realsky.md "Large frames"): the guided admission's chance estimate is summed over blocks of
candidates, so its memory is bounded by :data:`hostlink.images.guided.CHANCE_BLOCK_PAIRS` pairs whatever the counts
of candidates and predicted stars, and the blocks give the one-matrix sum."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hostlink.images import guided


def _inputs(n_cand: int, n_star: int, seed: int = 3):
    rng = np.random.default_rng(seed)
    sigma = rng.uniform(0.05, 0.8, n_cand)
    own = sigma * rng.uniform(0.5, 1.0, n_cand)
    mag = rng.uniform(-8.0, -2.0, n_cand)
    predicted = rng.uniform(-8.0, -2.0, n_star)
    sigma_ref = np.where(rng.random(n_star) < 0.1, rng.uniform(0.1, 0.5, n_star), 0.0)
    return (mag, sigma, own), (predicted, sigma_ref)


def _one_matrix(cands, stars, sigma_pred, window, area):
    """The estimate as one candidates x stars matrix (the formula of guided._chance_expected written out)."""
    mag, sigma, own = cands
    predicted, sigma_ref = stars
    row_px = np.where(sigma_ref[None, :] > 0, own[:, None], sigma[:, None])
    radius = guided.CONTAINMENT_SIGMAS * np.sqrt(sigma_pred**2 + row_px**2 + sigma_ref[None, :] ** 2)
    agree = np.abs(mag[:, None] - predicted[None, :]) <= window
    return float(np.sum(agree * (math.pi * radius**2)) / area)


def test_chance_blocks_give_the_one_matrix_sum(monkeypatch):
    cands, stars = _inputs(1234, 567)
    whole = _one_matrix(cands, stars, 0.3, 0.8, 6000 * 4000)
    # one block (the default budget holds these 0.7 M pairs): the same operations, bit for bit
    assert guided._chance_expected(cands, stars, 0.3, 0.8, 6000 * 4000) == whole
    # many blocks: only the order of the additions differs (float64 rounding, ~1e-16 per addition)
    monkeypatch.setattr(guided, "CHANCE_BLOCK_PAIRS", 10_000)
    blocked = guided._chance_expected(cands, stars, 0.3, 0.8, 6000 * 4000)
    assert blocked == pytest.approx(whole, rel=1e-12)


def test_chance_memory_bounded_by_the_block(monkeypatch):
    """Every candidate x star array formed holds at most CHANCE_BLOCK_PAIRS entries (counted, not timed), for a
    frame whose whole matrix is 50 times that."""
    monkeypatch.setattr(guided, "CHANCE_BLOCK_PAIRS", 20_000)
    shapes = []
    original = guided._row_sigma_px

    def counting(sigma_px, own_px, sigma_ref):
        out = original(sigma_px, own_px, sigma_ref)
        shapes.append(out.size)
        return out

    monkeypatch.setattr(guided, "_row_sigma_px", counting)
    cands, stars = _inputs(2000, 500)
    guided._chance_expected(cands, stars, 0.3, 0.8, 1.0e6)
    assert len(shapes) == 50
    assert max(shapes) <= 20_000
    assert sum(shapes) == 2000 * 500


def test_chance_without_candidates_or_stars_is_zero():
    cands, stars = _inputs(0, 10)
    assert guided._chance_expected(cands, stars, 0.3, 0.8, 1.0e6) == 0.0
    cands, stars = _inputs(10, 0)
    assert guided._chance_expected(cands, stars, 0.3, 0.8, 1.0e6) == 0.0
