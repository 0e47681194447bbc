"""Batch-size entries of bench_throughput (`sharding.parse_batch_devices`): B (the most
devices dividing B) or B:D (B envs over the first D devices); every bad entry is refused
with its reason before anything runs."""

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
