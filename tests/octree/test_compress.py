"""Compression by measured error (``octree compress --data D --target-db``) and k-means codebooks."""
from __future__ import annotations

import json

import numpy as np
import pytest

from nerfbake.cli import main
from nerfbake.data.formats import load_dataset
from nerfbake.octree.compress import QUALITY_FLOOR_DB, compress_tree, kmeans_refine, median_cut
from nerfbake.octree.evaluate import ViewLoss
from nerfbake.octree.io import load_tree, volrend_problems


def test_kmeans_refinement_lowers_the_error_of_median_cut_at_the_same_size():
    rng = np.random.default_rng(1)
    # view-dependent residuals: a dense clump near zero plus a sparse spread of large values
    x = np.concatenate([rng.normal(0, 0.01, (20000, 3)), rng.normal(0, 0.5, (2000, 3))]).astype(np.float32)
    book, idx = median_cut(x, 6)
    err_mc = np.mean((book[idx] - x) ** 2)
    kbook, kidx = kmeans_refine(x, book, idx, 4)
    err_km = np.mean((kbook[kidx] - x) ** 2)
    assert err_km < 0.7 * err_mc
    for k in np.unique(kidx):  # every used entry is the mean of its members
        assert np.allclose(kbook[k], x[kidx == k].mean(0), atol=1e-5)
    assert set(np.unique(kidx)) <= set(np.unique(idx))  # unused entries stay unused: indices stay within the budget


def test_a_deep_median_cut_holds_every_shallower_one():
    """The search reads a b-bit cut off one 16-bit cut (index >> (16 - b)); that is only right if median cut
    splits each cell into cells 2k and 2k + 1, also where --min-extent stops a split."""
    x = np.random.default_rng(2).normal(size=(3000, 3)).astype(np.float32)
    x[:500] *= 1e-4
    for extent in (0.0, 1e-2):
        deep = median_cut(x, 12, extent)[1]
        for b in (1, 4, 7):
            assert np.array_equal(median_cut(x, b, extent)[1], deep >> (12 - b))


def test_measured_allocation_keeps_its_target_and_is_what_the_file_holds(tiny_tree, tiny_scene, tmp_path, capsys):
    loose = compress_tree(tiny_tree, tmp_path / "loose.npz", data=tiny_scene, target_db=0.5, views=2, sigma_thresh=0.1)
    assert loose["allocation"] == "measured" and loose["target_met"] and loose["measured_loss_db"] <= 0.5
    assert volrend_problems(tmp_path / "loose.npz") == []
    # the loss measured while choosing is the loss of the file a reader loads
    ds = load_dataset(tiny_scene)
    raw = load_tree(tiny_tree)
    loss = ViewLoss(raw, ds, 2, quality_floor_db=QUALITY_FLOOR_DB)
    assert loss(load_tree(tmp_path / "loose.npz")) == pytest.approx(loose["measured_loss_db"], abs=1e-4)
    # the search went below 16 bits somewhere, and tried at least one rung that broke the target or hit the ladder's end
    assert min(loose["band_bits"]) < 16
    assert any(t["loss_db"] > 0.5 for t in loose["tried"]) or min(loose["band_bits"]) == 2
    full = compress_tree(tiny_tree, tmp_path / "full.npz", band_bits=(16,), sigma_thresh=0.1)
    assert loose["file_bytes"] < full["file_bytes"]
    tight = compress_tree(tiny_tree, tmp_path / "tight.npz", data=tiny_scene, target_db=0.02, views=2, sigma_thresh=0.1)
    assert tight["measured_loss_db"] <= max(0.02, tight["tried"][0]["loss_db"])
    assert tight["file_bytes"] >= loose["file_bytes"] * 0.98  # a tighter target never buys a (much) smaller file

    # the CLI prints the choice and keeps it in --json
    assert main(["octree", "compress", "--tree", str(tiny_tree), "--out", str(tmp_path / "cli.npz"), "--data",
                 str(tiny_scene), "--views", "2", "--sigma-thresh", "0.1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["allocation"] == "measured" and out["target_db"] == 0.5 and "measured_loss_db" in out
    assert main(["octree", "info", str(tmp_path / "cli.npz"), "--json"]) == 0  # the file keeps the choice
    info = json.loads(capsys.readouterr().out)
    assert info["volrend_problems"] == [] and info["compression"]["band_bits"] == out["band_bits"]
    assert info["compression"]["measured_loss_db"] == pytest.approx(out["measured_loss_db"])
    assert main(["octree", "compress", "--tree", str(tiny_tree), "--out", str(tmp_path / "fixed.npz"), "--sigma-thresh", "0.1"]) == 0
    assert "no --data" in capsys.readouterr().out


def test_a_poor_tree_keeps_its_colours(tiny_tree, tiny_scene, tmp_path):
    """Against the photos alone a poor tree hides the error compression adds (a 13 dB room lost 0.2 dB with 4 colours
    for its diffuse band and its hues shifted); the added error is charged as if the tree scored QUALITY_FLOOR_DB."""
    ds, raw = load_dataset(tiny_scene), load_tree(tiny_tree)
    loss = ViewLoss(raw, ds, 2, quality_floor_db=QUALITY_FLOOR_DB)
    assert loss.reference < QUALITY_FLOOR_DB  # the case this guards: a tree below the floor
    out = compress_tree(tiny_tree, tmp_path / "c.npz", data=tiny_scene, target_db=0.5, views=2, sigma_thresh=0.1)
    assert out["target_met"]
    added = np.mean([np.mean((c - r) ** 2) for c, r in zip(loss.renders(load_tree(tmp_path / "c.npz")),
                                                            loss.first_renders)])
    assert added <= (10 ** (0.5 / 10) - 1) * 10 ** (-QUALITY_FLOOR_DB / 10) * 1.001
    # a 2-bit diffuse band costs this tree more under the floor than its drop against the photos says
    two_bits = compress_tree(tiny_tree, tmp_path / "two.npz", band_bits=(2,), sigma_thresh=0.1)
    coarse = load_tree(two_bits["tree"])
    assert ViewLoss(raw, ds, 2)(coarse) < loss(coarse)


def test_a_threshold_that_drops_too_much_is_lowered_before_the_bands_are_chosen(tiny_tree, tiny_scene, tmp_path):
    """Dropping the fainter half of this tree's leaves costs more than half the target by itself, which would leave
    the bands nothing to spend (the phone clip's tree at sigma 2 kept 16 bits everywhere); the search lowers the
    threshold first and still meets the target."""
    tree = load_tree(tiny_tree)
    sigma = tree.data[..., -1][(tree.child == 0) & (tree.data[..., -1] > 0)].numpy()
    median = float(np.median(sigma))
    out = compress_tree(tiny_tree, tmp_path / "c.npz", data=tiny_scene, target_db=0.5, views=2, sigma_thresh=median)
    first = out["tried"][0]
    assert first["sigma_thresh"] == median and first["loss_db"] > 0.25  # the case this guards
    assert out["sigma_thresh"] < median and out["target_met"]
    assert min(out["bits_per_band"]) < 16  # the bands got room


def test_compression_benchmark_prints_every_row(tiny_tree, tiny_scene, tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    res = subprocess.run([sys.executable, str(root / "benchmarks" / "octree_compress.py"), "--tree", str(tiny_tree),
                          "--data", str(tiny_scene), "--out", str(tmp_path / "c"), "--eval-views", "2",
                          "--fixed", "16,8,6,4", "--codebooks", "median", "--sigma-thresh", "0.1"],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    out = json.loads(res.stdout)
    assert [r["name"] for r in out["results"]] == ["default", "16,8,6,4 median", "authors"]
    for r in out["results"]:
        assert r["volrend_ok"] and r["ratio"] > 1 and np.isfinite(r["test_loss_db"])
    assert out["results"][0]["train_loss_db"] <= out["target_db"]
    assert out["results"][2]["band_bits"] == [16] * 9


def test_candidates_decode_as_the_reader_decodes_their_file():
    """The search re-decodes only what changed between candidates; after any sequence of allocations, thresholds
    and codebooks the candidate must equal what the reader makes of that allocation's arrays."""
    import torch

    from nerfbake.octree.compress import Quantizer, basis_bits
    from nerfbake.octree.io import tree_from_arrays
    from tests.octree.test_octree import random_tree

    tree = random_tree(28, seed=7, cells=2000, depth=4)
    tree.data[..., -1] *= 10  # densities either side of the thresholds below
    q = Quantizer(tree, 9, 16, 2.0, 2.0 ** -9, "kmeans")
    steps = [([16, 16, 16], "median", 2.0), ([16, 6, 4], "median", 2.0), ([16, 6, 2], "median", 4.0),
             ([12, 6, 2], "kmeans", 4.0), ([12, 6, 2], "kmeans", 8.0)]
    for retain in (0, 1):
        for bands, codebook, thresh in steps:
            q.codebook = codebook
            per_basis = basis_bits(9, 16, bands)
            got = q.decoded(per_basis, retain, thresh).data
            want = tree_from_arrays("x", q.arrays(per_basis, retain, thresh)).data
            assert torch.equal(got, want), (retain, bands, codebook, thresh)
