"""Review 32: ``hubconf.py`` and ``cva-demo`` (each a regression test of a fault found there):
typing names listed as hub entries, and a ``pretrained`` that is no bool."""

from __future__ import annotations

import importlib.util
from pathlib import Path
import re

import pytest

torch = pytest.importorskip('torch')

from cva_confidence_ros.errors import ConfigError  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
ENTRIES = ['ccnn', 'cvanet', 'cvanet_fast', 'cvanet_lite', 'lfn', 'lgcnet', 'pipeline']


def _hub(entry: str, **options: object) -> object:
    return torch.hub.load(str(ROOT), entry, source='local', verbose=False, **options)


def test_the_hub_lists_only_its_entries() -> None:
    # torch.hub.list takes every callable of hubconf.py whose name does not start with '_':
    # it named the typing imports 'Any' and 'Callable' as entries too (torch.hub.load of 'Any'
    # then said "Any cannot be instantiated", torch.hub.help a TypeError).
    spec = importlib.util.spec_from_file_location('hubconf_under_test', ROOT / 'hubconf.py')
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    listed = sorted(
        name for name in dir(module)
        if callable(getattr(module, name)) and not name.startswith('_')
    )
    assert listed == ENTRIES


@pytest.mark.parametrize('pretrained', ['False', 'no', 0, 1, None])
def test_a_pretrained_that_is_no_bool_is_refused(pretrained: object) -> None:
    # pretrained='False' (a string from a config file) loaded the shipped weights; 0 and None
    # gave an untrained network without a word.
    with pytest.raises(ConfigError, match=re.escape(
            f'pretrained must be True or False; got {pretrained!r}')):
        _hub('cvanet_fast', pretrained=pretrained)

