"""Table 2 on splat pairs (``bench/bench_enhance.py --pairs``, issue 29): the bench reads a stored
PairDataset, trains only on its train split and scores only its test split (a user reads the
figures as held-out ones), and refuses a ref that is not a dataset it can score.

The dataset: three sub-sequences of one rendered path each (the hand-made drifting blob of
``tests/enhance/test_splat_pairs.py``, 64 px, 4 frames), split by ``split_subsequences``; the
bench at its ``--quick`` sizes with 2 training steps (4-11 s on the shared 2-core machine).
"""

from __future__ import annotations

import json

import pytest
import torch

from tests.enhance.test_splat_pairs import _sequence, blob, lq_of, path
from tests.gpu_machine import load_bench
from volcap_core.enhance.production import FacePairSet, PairDataset, split_subsequences
from volcap_core.records import ArtifactRef
from volcap_core.splat_pairs import render_path
from volcap_core.store import ArtifactStore

REF0 = ArtifactRef(digest="blake3:" + "b" * 64, size=1)


@pytest.fixture(scope="module")
def bench():
    return load_bench("bench_enhance")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """A stored three-sub-sequence PairDataset: (store URL, its ref, the dataset)."""
    torch.set_num_threads(1)
    hq, lq, views = blob(600), lq_of(blob(600)), path()
    hq_rgba, _ = render_path(hq, views)
    lq_rgba, lq_flow = render_path(lq, views, flow=True)
    rendered = (hq, lq, views, hq_rgba, lq_rgba, lq_flow)
    url = f"file://{tmp_path_factory.mktemp('pairs')}/store"
    s = ArtifactStore(url)
    ds = PairDataset(actor="anna", group="anna", capture=REF0, calibration=REF0, colour=None, method="splat",
                     lq_range=(100, 200), lq_range_source="preset", resolution=64, parameters={},
                     split=split_subsequences(3, seed=0), sequences=tuple(_sequence(s, rendered, i) for i in range(3)))
    return url, s.put_record(ds), ds


def test_the_bench_trains_on_the_train_split_and_scores_the_test_split(bench, dataset, tmp_path, monkeypatch):
    import volcap_core.enhance.training as training

    url, ref, ds = dataset
    trained_on = []
    real = training.train_enhancer

    def recording(model, pairs, *a, **kw):   # the real training, recording what it is given
        trained_on.append([p.name for p in pairs])
        return real(model, pairs, *a, **kw)

    monkeypatch.setattr(training, "train_enhancer", recording)
    out = tmp_path / "out.json"
    result = bench.main(["--quick", "--pairs", url, ref.digest, "--vae-steps", "2", "--steps", "2",
                         "--sample-steps", "2", "--json", str(out), "--sheets", str(tmp_path / "img")])

    train = {f"anna/s{i:03d}-p000" for i in ds.split["train"]}
    test = {f"anna/s{i:03d}-p000" for i in ds.split["test"]}
    assert train and test and not train & test
    assert [set(names) for names in trained_on] == [train, train]          # the full and the image model
    rows = ["LQ input", "bicubic/unsharp", "untrained", "VAE round trip of HQ", "full", "full, from noise",
            "w/o OFW", "w/o OFW, w/o LFS"]
    assert list(result["table"]) == rows
    assert all(set(result["per_sequence"][m]) == test for m in rows)   # every figure is on the test split
    # the fit: the input and the trained models on the training split's sequences, apart
    assert {m: set(v) for m, v in result["train_split_psnr"].items()} == {m: train for m in ("LQ input", "full",
                                                                                             "w/o OFW")}
    assert set(result["data"]["test_sequences"]) == test and set(result["data"]["train_sequences"]) == train
    assert result["data"]["split_subsequences"]["test"] == list(ds.split["test"])
    assert json.loads(out.read_text())["table"]["full"]["psnr"] == pytest.approx(result["table"]["full"]["psnr"])
    assert {p.rsplit("/", 1)[-1] for p in result["sheets"]} == {"enhance_pairs_heldout.jpg",
                                                                  "enhance_pairs_ablations.jpg"}


def test_a_ref_that_is_not_a_pair_dataset_or_has_no_test_split_is_named(bench, dataset):
    url, ref, ds = dataset
    s = ArtifactStore(url)
    interim = s.put_record(FacePairSet(actor="anna", group="anna", capture=REF0, method="interim", parameters={},
                                       sequences=()))
    with pytest.raises(SystemExit, match=f"{interim.digest}: a face-pair-set record"):
        bench.load_pair_dataset(url, interim.digest)
    empty = s.put_record(ds.model_copy(update={"split": {**ds.split, "test": ()}}))
    s.set_ref("datasets/no-test", empty)
    with pytest.raises(SystemExit, match="datasets/no-test: the test split of PairDataset .* is empty"):
        bench.load_pair_dataset(url, "datasets/no-test")
    with pytest.raises(SystemExit, match="datasets/none: no ref named 'datasets/none'"):
        bench.load_pair_dataset(url, "datasets/none")
    other = s.put_bytes(b"{}", "application/json")
    with pytest.raises(SystemExit, match=f"{other.digest}: not a PairDataset"):
        bench.load_pair_dataset(url, other.digest)
