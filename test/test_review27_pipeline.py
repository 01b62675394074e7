"""Review 27: the stamp synchroniser's tightest set and option types, and the pipeline's option
types and the mask size that ``output_region`` takes."""

from __future__ import annotations

import itertools
from pathlib import Path
import random

import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline, output_region
from cva_confidence_ros.sync import StampSynchronizer


def test_approximate_takes_the_tightest_set_not_the_one_nearest_the_new_stamp() -> None:
    # With a@5 the sets {5, 7, 0} (spread 7) and {5, 2, 0} (spread 5) fit a tolerance of 10;
    # the set nearest a@5 on every key used to be taken.
    sync = StampSynchronizer(('a', 'b', 'c'), approximate=True, tolerance_ns=10)
    sync.add('b', 2, 'b2')
    sync.add('b', 7, 'b7')
    sync.add('c', 0, 'c0')
    (matched,) = sync.add('a', 5, 'a5')
    assert matched.stamps_ns == {'a': 5, 'b': 2, 'c': 0}
    assert matched.items == {'a': 'a5', 'b': 'b2', 'c': 'c0'}
    assert sync.pending() == {'a': 0, 'b': 1, 'c': 0}  # b7 waits for a later set


def test_approximate_spread_is_the_smallest_of_all_sets_by_brute_force() -> None:
    rng = random.Random(27)
    for _ in range(300):
        keys = ('a', 'b', 'c', 'd')[: rng.randint(2, 4)]
        tolerance = rng.randint(0, 8)
        sync = StampSynchronizer(keys, queue_size=8, approximate=True, tolerance_ns=tolerance)
        *others, last = keys
        waiting = {key: sorted(rng.sample(range(-10, 10), rng.randint(1, 3))) for key in others}
        for key in others:
            for stamp in waiting[key]:
                sync.add(key, stamp, stamp)
        # Nothing of the last key waits: no set can be complete before its message.
        assert sum(sync.pending().values()) == sum(len(s) for s in waiting.values())
        stamp = rng.randint(-10, 10)
        fits = [
            max(combo) - min(combo)
            for combo in itertools.product(*waiting.values(), [stamp])
            if max(combo) - min(combo) <= tolerance
        ]
        out = sync.add(last, stamp, stamp)
        if not fits:
            assert out == []
            continue
        (matched,) = out
        spread = max(matched.stamps_ns.values()) - min(matched.stamps_ns.values())
        assert spread == min(fits), (waiting, stamp, tolerance, matched.stamps_ns)


def test_numpy_integer_stamps_and_sizes_are_integers() -> None:
    # Refused before with "must be an integer ...; got np.int64(5)", unlike every other
    # option of the package (checks.is_int).
    sync = StampSynchronizer(
        ('a', 'b'), queue_size=np.int64(3), approximate=True, tolerance_ns=np.int32(2),
        min_jump_ns=np.uint32(10),
    )
    assert sync.add('a', np.int64(5), 'a') == []
    (matched,) = sync.add('b', np.uint64(6), 'b')
    assert matched.stamps_ns == {'a': 5, 'b': 6}
    assert all(type(stamp) is int for stamp in matched.stamps_ns.values())
    assert type(matched.stamp_ns) is int
    with pytest.raises(InputError, match='stamp_ns must be an integer'):
        sync.add('a', np.float64(7.0), 'a')
    with pytest.raises(InputError, match='stamp_ns must be an integer'):
        sync.add('a', np.bool_(True), 'a')


@pytest.mark.parametrize('name', ['approximate', 'record_drops'])
@pytest.mark.parametrize('value', ['false', 'False', 1, 0, None])
def test_synchroniser_flags_must_be_bools(name: str, value: object) -> None:
    # bool('false') is True: StampSynchronizer(approximate='false') paired approximately.
    with pytest.raises(ConfigError, match=f'{name} must be True or False; got {value!r}'):
        StampSynchronizer(('a', 'b'), **{name: value})  # type: ignore[arg-type]
    assert StampSynchronizer(('a', 'b'), **{name: np.bool_(True)}).approximate is (
        name == 'approximate'
    )


def test_one_string_is_no_list_of_keys() -> None:
    # tuple('left') made the four streams 'l', 'e', 'f' and 't'.
    with pytest.raises(ConfigError, match="keys must be a sequence of stream names, not one "
                                          "string; got 'left'"):
        StampSynchronizer('left')
    assert StampSynchronizer(['left']).keys == ('left',)


@pytest.mark.parametrize('value', ['false', 'no', 1, None])
def test_lr_check_must_be_a_bool(value: object) -> None:
    # lr_check='false' switched the left-right check on (152 of 2048 pixels NaN on a 32×64
    # pair) without a word.
    with pytest.raises(ConfigError, match=f'lr_check must be True or False; got {value!r}'):
        PipelineConfig(confidence_method='pkrn', lr_check=value)  # type: ignore[arg-type]
    assert PipelineConfig(confidence_method='pkrn', lr_check=np.bool_(True)).lr_check


@pytest.mark.parametrize(
    ('changes', 'message'),
    [
        ({'matcher': ['census_bm']}, r"matcher must be a string; got \['census_bm'\]"),
        ({'confidence_method': {'pkrn'}}, r"confidence_method must be a string; got \{'pkrn'\}"),
        ({'model_path': 5}, r'model_path must be a string \(a file\); got 5$'),
        ({'model_path': Path('w.pt')},
         r"model_path must be a string \(a file\); got .*'w.pt'\); pass str\(path\)"),
    ],
)
def test_names_and_paths_of_another_type_are_named(changes: dict, message: str) -> None:
    # An unhashable name failed the registry look-up with "unhashable type: 'list'"; an int
    # model_path got through the config and failed in the weights loader with a TypeError.
    with pytest.raises(ConfigError, match=message):
        PipelineConfig(confidence_method='pkrn').replace(**changes)


def test_model_path_of_another_type_never_reaches_the_weights_loader() -> None:
    with pytest.raises(ConfigError, match='model_path must be a string'):
        StereoPipeline(PipelineConfig(matcher='census_bm', max_disparity=64, device='cpu',
                                      model_path=5))  # type: ignore[arg-type]


def test_output_region_refuses_a_mask_of_another_resolution() -> None:
    config = PipelineConfig(confidence_method='pkrn', downsample=2)
    mask = np.ones((64, 128), bool)
    mask[:, :16] = False
    region = output_region(config, (32, 64), mask)
    assert region is not None and not region[:, :8].any() and region[:, 8:].all()
    # Twice the size: it used to be cropped to its top-left quarter, so that the ignored
    # columns 200… vanished and every output pixel counted as judged.
    large = np.ones((128, 256), bool)
    large[:, 200:] = False
    with pytest.raises(InputError, match=r'the mask \(mask_path\) is 256×128 px \(128×64 px at '
                                         r'downsample = 2\) but the outputs are 64×32 px'):
        output_region(config, (32, 64), large)
    # Smaller: numpy's "could not broadcast input array from shape (16,32) into (16,64)".
    with pytest.raises(InputError, match=r'is 64×32 px \(32×16 px at downsample = 2\)'):
        output_region(config, (32, 64), np.ones((32, 64), bool))
    with pytest.raises(InputError, match=r'is 65×32 px but the outputs are 64×32 px'):
        output_region(config.replace(downsample=1), (32, 64), np.ones((32, 65), bool))
    # Still taken: the mask of an odd input size, 35×71 px at downsample 4, is cropped as the
    # pipeline crops the images (to 32×68, outputs of 8×17).
    mask = np.ones((35, 71), bool)
    mask[:, :8] = False
    region = output_region(PipelineConfig(confidence_method='pkrn', downsample=4), (8, 17), mask)
    assert region is not None and region.shape == (8, 17)
    assert not region[:, :2].any() and region[:, 2:].all()
