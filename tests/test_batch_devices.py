"""Batch-size entries of bench_throughput (`sharding.parse_batch_devices`): B (the most
devices dividing B) or B:D (B envs over the first D devices); every bad entry is refused
with its reason before anything runs; and the evaluator's check that the env batch divides
over the devices it is sharded on."""

import types

import pytest

from heisd_jax import sharding


def test_batch_sizes_parse_to_envs_and_devices():
    assert sharding.parse_batch_devices(["1", "64", "256:1"], available=1) == [(1, 1), (64, 1), (256, 1)]
    assert sharding.parse_batch_devices(["1", "6", "8"], available=4) == [(1, 1), (6, 3), (8, 4)]  # plain B: most dividing
    assert sharding.parse_batch_devices(["1024:1", "1024:2", "2048:2"], available=2) == [(1024, 1), (1024, 2), (2048, 2)]


@pytest.mark.parametrize("entry, reason", [
    ("x", "not B or B:D"), ("0", "not B or B:D"), ("4:0", "not B or B:D"), ("4:2:1", "not B or B:D"),
    ("4:3", "asks for 3 devices; 2 are available"), ("3:2", "cannot be split evenly over 2 devices"),
])
def test_bad_batch_sizes_are_refused_with_the_reason(entry, reason):
    with pytest.raises(ValueError, match=reason):
        sharding.parse_batch_devices(["8", entry], available=2)


def test_num_envs_must_divide_over_the_mesh():
    """The evaluator's check (a stand-in mesh: it reads only the device count)."""
    four = types.SimpleNamespace(size=4)
    sharding.check_batch(8, four)
    sharding.check_batch(3, types.SimpleNamespace(size=1))  # one device takes any batch
    with pytest.raises(ValueError, match="num_envs=6 is not divisible by the 4 devices.*multiple of 4"):
        sharding.check_batch(6, four)
