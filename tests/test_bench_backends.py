"""bench/bench_backends.py: its configurations and its table of medians (no timing)."""

import importlib.util
import os

import pytest

PATH = os.path.join(os.path.dirname(os.path.dirname(__file__)), "bench", "bench_backends.py")
spec = importlib.util.spec_from_file_location("bench_backends", PATH)
bench = importlib.util.module_from_spec(spec)
spec.loader.exec_module(bench)


def _result(samples, matmul, achieved=None):
    result = {"first_epoch_s": 10.0, "samples_per_s": samples, "matmul_gflops": matmul,
              "predict_pairs_per_s": 3 * samples}
    if achieved is not None:
        result["achieved_gflops"] = achieved
    return result


def test_table_takes_medians_and_compares_with_tensorflow():
    results = {"jax": [_result(10, 100, 50), _result(12, 100, 60), _result(30, 100, 70)],
               "tensorflow": [_result(5, 200, 25), _result(5, 200, 25)],
               "torch": [_result(4, 300)]}
    lines = bench.table(results, ["jax", "tensorflow", "torch"]).splitlines()
    jax = [c.strip() for c in lines[2].strip("|").split("|")]
    assert jax[:6] == ["jax", "10.0", "12.00", "60.0", "100.0", "0.60"]
    assert jax[7] == "2.40x"  # 12 / 5
    torch = [c.strip() for c in lines[4].strip("|").split("|")]
    assert torch[3] == "n/a" and torch[5] == "n/a" and torch[7] == "0.80x"


def test_jax_flag_rows_and_bad_flags():
    args = bench.parse_args(["--backends", "jax", "--jax-flags", "x=--xla_cpu_use_xnnpack=true"])
    assert bench.configurations(args) == [
        ("jax", "jax", {}, []), ("jax+x", "jax", {"XLA_FLAGS": "--xla_cpu_use_xnnpack=true"}, [])]
    with pytest.raises(SystemExit):
        bench.parse_args(["--jax-flags", "no-equals-sign"])
    with pytest.raises(SystemExit):
        bench.parse_args(["--rounds", "0"])


def test_plain_conv_and_bf16_rows():
    args = bench.parse_args(["--backends", "jax", "tensorflow", "--plain-conv-row",
                             "--bf16", "tensorflow"])
    assert bench.configurations(args) == [
        ("jax", "jax", {}, []), ("tensorflow", "tensorflow", {}, []),
        ("jax+plain-conv", "jax", {}, ["--plain-conv"]),
        ("tensorflow+bf16", "tensorflow", {}, ["--dtype-policy", "mixed_bfloat16"])]
    with pytest.raises(SystemExit):
        bench.parse_args(["--bf16", "mxnet"])
