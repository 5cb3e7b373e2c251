"""``bench/generalisation.py --model DIRECTION=FILE``: a model of one's own is scored only where it is held out.

The checks run on real model files (the shipped weights, re-saved with other training recordings in their
metadata); the command-line errors themselves are in tests/test_bench_args.py."""

from __future__ import annotations

import copy
import hashlib
import importlib.util
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def generalisation():
    spec = importlib.util.spec_from_file_location("bench_generalisation", REPO / "bench" / "generalisation.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """Model files trained (says their metadata) on K729 only, and on recordings it does not name."""
    from stages.lib.ar import DEFAULT_MODEL_PATH, load_model, save_model

    folder = tmp_path_factory.mktemp("models")
    shipped = load_model(DEFAULT_MODEL_PATH)
    k729 = copy.deepcopy(shipped)
    k729.metadata = {**k729.metadata, "recordings": ["k729_2022-03-16"]}
    unnamed = copy.deepcopy(shipped)
    unnamed.metadata = {k: v for k, v in unnamed.metadata.items() if k != "recordings"}
    return {"k729": save_model(folder / "k729.pt", k729), "unnamed": save_model(folder / "unnamed.pt", unnamed),
            "shipped": Path(DEFAULT_MODEL_PATH)}


def test_a_model_is_taken_only_in_the_direction_that_holds_its_location_out(generalisation, models):
    given, warnings = generalisation.given_models([f"k729-k733={models['k729']}"])
    assert given == {"k729-k733": models["k729"].resolve()} and warnings == []
    for item in (f"k733-k729={models['k729']}", f"k729-k733={models['shipped']}", f"k733-k729={models['shipped']}"):
        with pytest.raises(ValueError, match="not held out"):
            generalisation.given_models([item])
    with pytest.raises(ValueError, match="given twice"):
        generalisation.given_models([f"k729-k733={models['k729']}", f"k729-k733={models['k729']}"])


def test_a_model_that_names_no_recordings_is_scored_with_a_warning(generalisation, models):
    given, warnings = generalisation.given_models([f"k733-k729={models['unnamed']}"])
    assert list(given) == ["k733-k729"]
    assert len(warnings) == 1 and "cannot check" in warnings[0] and "K729" in warnings[0]


def test_a_given_model_is_keyed_by_its_contents(generalisation, models):
    train = generalisation.given_model("k729_2022-03-16", 0, models["k729"])
    digest = hashlib.sha256(models["k729"].read_bytes()).hexdigest()
    assert train["given"] is True and train["sha256"] == digest and train["key"] == digest[:12]
    assert train["trained_on"] == ["k729_2022-03-16"] and train["model"] == str(models["k729"])
    assert train["model_kind"]["kind"] == "gru" and train["model_kind"]["parameters"] > 0
