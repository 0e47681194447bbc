"""The XLA flags `import envs` sets before JAX starts: the shipped autotuning results are
loaded only where the installed versions made them and JAX may use a GPU, and a user's own
setting wins."""

import json

import pytest

from envs import _xla

GPU_VERSIONS = "jax-cuda13-pjrt==0.11.2;jax-cuda13-plugin==0.11.2;jax==0.11.2;jaxlib==0.11.2"


@pytest.fixture
def shipped(tmp_path, monkeypatch):
    path = tmp_path / "xla_autotune.pbtxt"
    path.write_text("entries {\n}\n")
    path.with_suffix(".json").write_text(json.dumps({"versions": GPU_VERSIONS}))
    monkeypatch.setattr(_xla, "jax_versions", lambda: GPU_VERSIONS)
    monkeypatch.delenv("JAX_PLATFORMS", raising=False)
    return path


def test_loaded_only_with_the_versions_that_made_it(shipped, monkeypatch):
    assert _xla.shipped_autotune(shipped) == shipped
    monkeypatch.setattr(_xla, "jax_versions", lambda: GPU_VERSIONS.replace("0.11.2", "0.11.3"))
    assert _xla.shipped_autotune(shipped) is None


def test_not_loaded_without_a_gpu(shipped, monkeypatch):
    monkeypatch.setenv("JAX_PLATFORMS", "cpu")
    assert _xla.shipped_autotune(shipped) is None
    monkeypatch.setenv("JAX_PLATFORMS", "cuda,cpu")
    assert _xla.shipped_autotune(shipped) == shipped
    monkeypatch.delenv("JAX_PLATFORMS")
    cpu_only = "jax==0.11.2;jaxlib==0.11.2"
    shipped.with_suffix(".json").write_text(json.dumps({"versions": cpu_only}))
    monkeypatch.setattr(_xla, "jax_versions", lambda: cpu_only)
    assert _xla.shipped_autotune(shipped) is None


def test_not_loaded_without_its_record(shipped):
    shipped.with_suffix(".json").write_text("{not json")
    assert _xla.shipped_autotune(shipped) is None
    shipped.with_suffix(".json").unlink()
    assert _xla.shipped_autotune(shipped) is None


@pytest.mark.parametrize("user", ["", "--xla_gpu_load_autotune_results_from=", "--xla_gpu_load_autotune_results_from=/mine.pbtxt"])
def test_configure_adds_the_flag_unless_the_user_set_it(shipped, monkeypatch, user):
    monkeypatch.setattr(_xla, "SHIPPED_AUTOTUNE", shipped)
    monkeypatch.setattr(_xla, "supported", lambda flags: {name: True for name in flags})
    monkeypatch.setenv("XLA_FLAGS", user)
    _xla.configure()
    flags = _xla.os.environ["XLA_FLAGS"].split()
    assert "--xla_cpu_use_fusion_emitters=false" in flags
    loads = [f for f in flags if f.startswith(f"--{_xla.AUTOTUNE_FLAG}=")]
    assert loads == ([user] if user else [f"--{_xla.AUTOTUNE_FLAG}={shipped}"])


def test_ship_autotune_replaces_the_callers_load_and_dump():
    caller = ("--xla_gpu_autotune_level=2 --xla_gpu_load_autotune_results_from=/a.pbtxt "
              "--xla_gpu_dump_autotune_results_to=/b.pbtxt")
    assert _xla.with_autotune_files("/prev.pbtxt", "/next.pbtxt", caller).split() == [
        "--xla_gpu_autotune_level=2", "--xla_gpu_load_autotune_results_from=/prev.pbtxt",
        "--xla_gpu_dump_autotune_results_to=/next.pbtxt"]


def test_the_shipped_record_describes_the_shipped_file():
    record_path = _xla.SHIPPED_AUTOTUNE.with_suffix(".json")
    if not record_path.exists():
        pytest.skip("no autotuning results shipped")
    record = json.loads(record_path.read_text())
    text = _xla.SHIPPED_AUTOTUNE.read_text()
    assert record["entries"] == sum(line.startswith("entries {") for line in text.splitlines()) > 0
    assert "jaxlib==" in record["versions"] and "jax-cuda" in record["versions"]
    assert record["programs"] and record["devices"] == sorted({p["device"] for p in record["programs"]})
    assert all(p["command"].startswith("python -m experiments.evaluate ") for p in record["programs"])


def test_a_record_of_one_gpu_reads_as_that_gpus_programs():
    old = {"device": "NVIDIA H100 80GB HBM3", "programs": ["python -m experiments.evaluate --method=ar"]}
    new = {"devices": ["NVIDIA H200"], "programs": [{"device": "NVIDIA H200", "command": "python -m x"}]}
    assert _xla.record_programs(old) == [{"device": "NVIDIA H100 80GB HBM3",
                                          "command": "python -m experiments.evaluate --method=ar"}]
    assert _xla.record_programs(new) == new["programs"]
    assert _xla.record_programs({}) == []


def test_flags_are_probed_together_once_and_one_by_one_only_where_that_fails(tmp_path, monkeypatch):
    monkeypatch.setattr(_xla, "_CACHE", tmp_path / "xla_flag.json")
    probes = []

    def probe(flags):  # this XLA knows every flag but --b, and cannot read --e's value
        probes.append(flags)
        if "--e=" in flags:
            return None  # failed without naming an unknown flag
        return {f for f in flags.split() if f.startswith("--b=")}
    monkeypatch.setattr(_xla, "_probe", probe)
    assert _xla.supported({"a": "1", "c": "2"}) == {"a": True, "c": True}
    assert probes == ["--a=1 --c=2"]  # one child process for both
    assert _xla.supported({"a": "1", "b": "0", "d": "3"}) == {"a": True, "b": False, "d": True}
    assert probes[1:] == ["--b=0 --d=3"]  # --a cached; the child named --b: still one child
    assert _xla.supported({"d": "3", "e": "x", "f": "4"}) == {"d": True, "e": False, "f": True}
    assert probes[2:] == ["--e=x --f=4", "--e=x", "--f=4"]  # nothing named: one by one
    assert _xla.supported({"f": "4", "b": "0", "a": "1", "e": "x"}) == {"f": True, "b": False, "a": True, "e": False}
    assert len(probes) == 5  # every answer cached


def test_a_probe_starts_only_the_cpu_backend_and_names_the_unknown_flags(monkeypatch):
    monkeypatch.setenv("JAX_PLATFORMS", "cuda")  # without a GPU, a child that kept this would fail to start
    assert _xla._probe("") == set()
    assert _xla._probe("--xla_no_such_flag_heisd=1 --xla_nor_this_one=2") == {"--xla_no_such_flag_heisd=1",
                                                                             "--xla_nor_this_one=2"}
