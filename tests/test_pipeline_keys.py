"""Cache keys: what must change a key and what must not."""
from __future__ import annotations

import importlib.metadata
import math
import os
import tomllib
from dataclasses import dataclass

import pytest

from pipeline import hashing
from pipeline.canonical import canonical_json
from pipeline.dag import DagError, External, Step, compute_keys
from pipeline.hashing import InputMissingError
from pipeline.stage import ParamsError, Stage
from pipeline.store import Store
from tests.pipeline_stages import REGISTRY, CountStage


class CountV2(CountStage):
    version = "2"


@dataclass(frozen=True)
class DeviceParams:
    device: str = "cpu"


class DeviceStage(Stage):
    name = "device"
    version = "1"
    Params = DeviceParams
    packages = ("numpy", "surely-not-installed-pkg")

    def run(self, ctx):
        pass


class RuntimeStage(Stage):
    """Its result depends on a fact of the computing process (here an environment variable standing in for a
    CPU's code path): the fact enters the key, and a worker that differs must refuse to compute it."""

    name = "runtime"
    version = "1"
    Params = DeviceParams

    @classmethod
    def runtime_environment(cls, params):
        return {"code_path": os.environ.get("TEST_CODE_PATH", "vector")}

    def run(self, ctx):
        (ctx.out_dir / "out.txt").write_text(os.environ.get("TEST_CODE_PATH", "vector"))


REG = dict(REGISTRY, device="tests.test_pipeline_keys:DeviceStage", runtime="tests.test_pipeline_keys:RuntimeStage")


@pytest.fixture
def store(tmp_path):
    return Store(tmp_path / "cache")


def key(store, step, registry=REG):
    return compute_keys([step], registry=registry, store=store)[step].key


def test_canonical_json_spelling_and_order():
    a = canonical_json({"b": [1, 2.5, (3.0,)], "a": 0.1, "c": {"y": 1e-1, "x": True}})
    b = canonical_json({"c": {"x": True, "y": 0.1}, "a": 1e-1, "b": (1.0, 2.50, [3])})
    assert a == b == '{"a":0.1,"b":[1,2.5,[3]],"c":{"x":true,"y":0.1}}'
    assert canonical_json(1.0) == canonical_json(1) == "1"
    assert canonical_json(True) != canonical_json(1)          # bool is not an int here
    assert canonical_json(math.nan) == '{"float":"nan"}'
    with pytest.raises(TypeError, match="canonical"):
        canonical_json({"x": object()})


def test_param_order_float_spelling_and_defaults_do_not_change_key(store):
    base = key(store, Step("count", {"n": 5, "start": 2}))
    assert key(store, Step("count", {"start": 2, "n": 5})) == base
    # Floats as a user writes them in TOML: 1 vs 1.0, 0.1 vs 1e-1
    v1 = tomllib.loads("value = 1")["value"]
    v2 = tomllib.loads("value = 1.0")["value"]
    assert key(store, Step("add", {"value": v1})) == key(store, Step("add", {"value": v2}))
    t1 = tomllib.loads("value = 0.1")["value"]
    t2 = tomllib.loads("value = 1e-1")["value"]
    assert key(store, Step("add", {"value": t1})) == key(store, Step("add", {"value": t2}))
    # a default written out explicitly is the same invocation
    assert key(store, Step("count", {"n": 5})) == key(store, Step("count", {"n": 5, "start": 0}))


def test_semantic_changes_change_key(store, tmp_path):
    base = key(store, Step("count", {"n": 5}))
    assert key(store, Step("count", {"n": 6})) != base                                       # param
    assert key(store, Step("count", {"n": 5}), dict(REG, count="tests.test_pipeline_keys:CountV2")) != base
    left5, left6 = Step("count", {"n": 5}), Step("count", {"n": 6})
    assert key(store, Step("add", {}, {"left": left5})) != key(store, Step("add", {}, {"left": left6}))
    # upstream keys enter by input name: the same step as "left" or as "right" are different invocations
    assert key(store, Step("add", {}, {"left": left5})) != key(store, Step("add", {}, {"right": left5}))
    store.set_salt("poisoned-2026-11")
    assert key(store, Step("count", {"n": 5})) != base                                       # salt


def test_nonsemantic_param_does_not_change_key(store, tmp_path):
    base = key(store, Step("count", {"n": 5}))
    assert key(store, Step("count", {"n": 5, "trace": str(tmp_path / "t"), "step_seconds": 0.5})) == base


def test_input_content_not_path_enters_key(store, tmp_path):
    folder = tmp_path / "images"
    folder.mkdir()
    for i in range(3):
        (folder / f"{i}.png").write_bytes(bytes([i]) * 100)
    k1 = key(store, Step("digest", {}, {"source": External(folder)}))
    copy = tmp_path / "elsewhere"
    copy.mkdir()
    for p in folder.iterdir():
        (copy / p.name).write_bytes(p.read_bytes())
    assert key(store, Step("digest", {}, {"source": External(copy)})) == k1     # moved: same content
    (folder / "1.png").write_bytes(bytes([9]) * 100)                            # same size, new bytes
    assert key(store, Step("digest", {}, {"source": External(folder)})) != k1
    (copy / "1.png").rename(copy / "renamed.png")                               # names are content too
    assert key(store, Step("digest", {}, {"source": External(copy)})) != k1


def test_environment_fingerprint_packages_and_device(store):
    step = Step("device", {"device": "cuda"})
    inputs = compute_keys([step], registry=REG, store=store)[step].key_inputs
    env = inputs["environment"]
    assert env["packages"] == {"numpy": importlib.metadata.version("numpy"),
                               "surely-not-installed-pkg": "not-installed"}
    assert env["device"] == "cuda"
    assert key(store, Step("device", {"device": "cpu"})) != key(store, step)


def test_runtime_environment_enters_the_key(store, monkeypatch):
    step = Step("runtime", {})
    monkeypatch.setenv("TEST_CODE_PATH", "vector")
    keyed = compute_keys([step], registry=REG, store=store)[step]
    assert keyed.key_inputs["environment"]["runtime"] == {"code_path": "vector"}
    monkeypatch.setenv("TEST_CODE_PATH", "portable")
    assert key(store, step) != keyed.key


def test_a_worker_in_another_environment_refuses_to_compute(store, tmp_path, monkeypatch):
    from pipeline.dag import params_dict
    from pipeline.engine import Job, execute_job

    step = Step("runtime", {})
    monkeypatch.setenv("TEST_CODE_PATH", "vector")            # the driver plans on a "vector" machine
    keyed = compute_keys([step], registry=REG, store=store)[step]
    job = Job(key=keyed.key, stage_ref=REG["runtime"], params=params_dict(keyed.params), inputs={},
              key_inputs=keyed.key_inputs, label="runtime", log_path=str(tmp_path / "log.txt"),
              cache_root=str(store.root), quiet=True)
    monkeypatch.setenv("TEST_CODE_PATH", "portable")          # ... the worker takes another path
    outcome = execute_job(job)
    assert outcome.status == "failed" and outcome.user_error
    assert "runtime.code_path: key computed for 'vector', this worker has 'portable'" in outcome.error
    assert store.lookup(keyed.key) is None and not (store.tmp.exists() and any(store.tmp.iterdir()))
    monkeypatch.setenv("TEST_CODE_PATH", "vector")            # a matching worker computes and publishes it,
    outcome = execute_job(job)                                # recording its environment in the manifest
    assert outcome.status == "done"
    manifest = store.manifest(keyed.key)
    assert manifest["runtime"] == {"code_path": "vector"} and manifest["stage_version"] == "1"


def test_hash_memo_skips_rehashing_unchanged_files_but_not_fresh_ones(store, tmp_path, monkeypatch):
    folder = tmp_path / "imgs"
    folder.mkdir()
    old = 1_600_000_000
    for i in range(4):
        (folder / f"{i}.png").write_bytes(os.urandom(64))
        os.utime(folder / f"{i}.png", (old, old))
    calls = []
    real = hashing.sha256_file
    monkeypatch.setattr(hashing, "sha256_file", lambda p: calls.append(p) or real(p))
    writer = Store(store.root).hasher
    first = writer.hash_path(folder)
    writer.save()
    assert len(calls) == 4
    fresh_store = Store(store.root)                 # a new process: memo read back from disk
    assert fresh_store.hasher.hash_path(folder) == first
    assert len(calls) == 4                          # no file read again
    # a changed file (new mtime, within the racy window) is re-read and not trusted from the memo
    (folder / "2.png").write_bytes(os.urandom(64))
    assert fresh_store.hasher.hash_path(folder) != first
    assert len(calls) == 5
    fresh_store.hasher.hash_path(folder)
    assert len(calls) == 6                          # modified just now: never served from the memo


def test_bad_steps_are_user_errors_naming_the_problem(store, tmp_path):
    with pytest.raises(ParamsError, match="'lbl'.*unknown parameter.*iterations"):
        key(store, Step("count", {"iterations": 3}, label="lbl"))
    with pytest.raises(ParamsError, match="'n' must be int"):
        key(store, Step("count", {"n": "five"}, label="lbl"))
    with pytest.raises(DagError, match="input 'source' is not an upstream input"):
        key(store, Step("add", {}, {"source": Step("count", {})}))
    with pytest.raises(InputMissingError, match="nope"):
        key(store, Step("digest", {}, {"source": External(tmp_path / "nope")}))
    with pytest.raises(ValueError, match="unknown stage 'fitt'"):
        key(store, Step("fitt", {}))


def test_identical_invocations_share_a_key(store):
    a, b = Step("count", {"n": 3}, label="a"), Step("count", {"n": 3}, label="b")
    keyed = compute_keys([a, b], registry=REG, store=store)
    assert keyed[a].key == keyed[b].key and a is not b
