"""Review 37 of ``cva-train`` at scale: every scene's cost volume stays in memory, so a run
on all of KITTI at D = 256 (about 98 GB) was killed by the system after an hour of matching,
with no word. Now the start-up log says what the volumes take, a run they cannot fit into is
refused before any matching, and ``--volume-cache DIR`` keeps them on disk (bit-equal results).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from train_test_utils import TINY

from cva_confidence_ros.datasets.synthetic import synthetic_pair
from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.training import data, trainer
from cva_confidence_ros.training.cli import build_parser, main
from cva_confidence_ros.training.config import TrainConfig

#: One epoch of the tiny run.
ONE = [*TINY, '--epochs', '1', '--epochs-low-lr', '0']


def _tiny_need() -> int:
    """Bytes of the volumes of the tiny run: two 24×40 training pairs and one validation
    pair at D = 16 (synthetic pairs fit D: no halving)."""
    return 3 * data.volume_bytes(24, 40, 16)


def _no_matching(*_args, **_kwargs):
    raise AssertionError('a scene was matched')


def test_volume_bytes_is_the_allocation() -> None:
    scene = data.prepare_scene(synthetic_pair(0, 30, 44, 16), 'census_bm', 16)
    assert scene.volume.nbytes == data.volume_bytes(30, 44, 16) == 16 * 42 * 56 * 2


def test_volumes_that_do_not_fit_are_refused_before_matching(
    tmp_path: Path, monkeypatch, capsys
) -> None:
    need = _tiny_need()
    monkeypatch.setattr(trainer, 'available_memory', lambda: (need - 1, 'MemAvailable (test)'))
    monkeypatch.setattr(trainer, 'prepare_scene', _no_matching)
    assert main([*ONE, '--out', str(tmp_path / 'run')]) == 2
    err = capsys.readouterr().err
    assert 'cost volumes of this run take' in err and 'MemAvailable (test)' in err
    assert '--volume-cache DIR' in err and '--max-scenes' in err
    # Exactly the volumes' bytes fit: the estimate is the allocation.
    monkeypatch.undo()
    monkeypatch.setattr(trainer, 'available_memory', lambda: (need, 'MemAvailable (test)'))
    assert main([*ONE, '--out', str(tmp_path / 'fits')]) == 0
    log = (tmp_path / 'fits' / 'train.log').read_text()
    assert 'cost volumes (float16, D = 16): 2 training scenes' in log
    assert 'in memory for the whole run' in log


def test_every_local_process_holds_the_training_volumes(tmp_path: Path, monkeypatch) -> None:
    config = TrainConfig(synthetic=2, synthetic_size=(24, 40), max_disparity=16, out=str(tmp_path))
    loaders = trainer._load_samples(config, False)
    one = 2 * data.volume_bytes(24, 40, 16)
    monkeypatch.setattr(trainer, 'available_memory', lambda: (one + 1, 'test'))
    lines: list[str] = []
    trainer._plan_volumes(loaders, [], config, lines.append, None, processes=1)
    with pytest.raises(ConfigError, match=r'× 2 processes'):
        trainer._plan_volumes(loaders, [], config, lines.append, None, processes=2)


def _weights(path: Path) -> dict[str, torch.Tensor]:
    return torch.load(path, map_location='cpu', weights_only=False)['state_dict']


def test_volume_cache_trains_bit_for_bit_as_in_memory(tmp_path: Path, monkeypatch) -> None:
    cache = tmp_path / 'volumes'
    assert main([*ONE, '--out', str(tmp_path / 'mem'), '--weights-out',
                 str(tmp_path / 'mem.pt')]) == 0  # fmt: skip
    assert main([*ONE, '--out', str(tmp_path / 'disk'), '--weights-out',
                 str(tmp_path / 'disk.pt'), '--volume-cache', str(cache)]) == 0  # fmt: skip
    assert len(list(cache.glob('*.npy'))) == 3  # two training pairs, one validation pair
    mem, disk = _weights(tmp_path / 'mem.pt'), _weights(tmp_path / 'disk.pt')
    assert all(torch.equal(mem[key], disk[key]) for key in mem)
    history = [
        trainer.json.loads((tmp_path / run / 'history.json').read_text())
        for run in ('mem', 'disk')
    ]
    assert [r['train_loss'] for r in history[0]] == [r['train_loss'] for r in history[1]]
    assert [r['val_auc'] for r in history[0]] == [r['val_auc'] for r in history[1]]
    # A resume (and any later run on the pairs) takes the volumes from the cache unmatched.
    monkeypatch.setattr(data, 'match_and_label', _no_matching)
    assert main([*TINY, '--epochs', '2', '--epochs-low-lr', '0', '--resume', '--out',
                 str(tmp_path / 'disk'), '--volume-cache', str(cache)]) == 0  # fmt: skip
    log = (tmp_path / 'disk' / 'train.log').read_text()
    assert 'of it there already' in log and 'epoch 2/2' in log


def test_a_stale_cache_entry_is_matched_again_and_said(tmp_path: Path) -> None:
    cache = tmp_path / 'volumes'
    assert main([*ONE, '--out', str(tmp_path / 'a'), '--volume-cache', str(cache)]) == 0
    first = sorted(cache.glob('*.npy'))[0]
    first.write_bytes(first.read_bytes()[:200])  # cut short (a full disk, a killed copy)
    cut = sorted(cache.glob('*.labels.npz'))[2]
    cut.write_bytes(cut.read_bytes()[:100])
    labels = sorted(cache.glob('*.labels.npz'))[1]
    with np.load(labels) as stored:
        parts = dict(stored)
    meta = trainer.json.loads(str(parts['meta']))
    parts['meta'] = np.array(trainer.json.dumps({**meta, 'version': '0.0.0'}))
    with open(labels, 'wb') as handle:
        np.savez(handle, **parts)  # written by another version of the matchers
    assert main([*ONE, '--out', str(tmp_path / 'b'), '--volume-cache', str(cache)]) == 0
    log = (tmp_path / 'b' / 'train.log').read_text()
    assert log.count('is stale') == 3 and 'matched again' in log
    assert "made with other version ('0.0.0'" in log
    history = [
        trainer.json.loads((tmp_path / run / 'history.json').read_text()) for run in 'ab'
    ]
    assert history[0][0]['train_loss'] == history[1][0]['train_loss']


def test_volume_cache_on_a_full_disk_is_refused_before_matching(
    tmp_path: Path, monkeypatch, capsys
) -> None:
    monkeypatch.setattr(trainer.shutil, 'disk_usage', lambda _: type('U', (), {'free': 1000}))
    monkeypatch.setattr(data, 'match_and_label', _no_matching)
    assert main([*ONE, '--out', str(tmp_path / 'run'), '--volume-cache',
                 str(tmp_path / 'volumes')]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert '--volume-cache' in err and 'still to write take' in err


def test_available_memory_takes_a_cgroup_limit(tmp_path: Path) -> None:
    v1 = tmp_path / 'v1' / 'memory'
    v1.mkdir(parents=True)
    (v1 / 'memory.limit_in_bytes').write_text('4000000\n')
    (v1 / 'memory.usage_in_bytes').write_text('3000000\n')
    (v1 / 'memory.stat').write_text('cache 5\ntotal_inactive_file 500000\n')
    left, source = trainer.available_memory(tmp_path / 'v1')
    assert left == 1_500_000 and 'cgroup limit' in source
    v2 = tmp_path / 'v2'
    v2.mkdir()
    (v2 / 'memory.max').write_text('max\n')  # no limit: MemAvailable decides
    (v2 / 'memory.current').write_text('3000000\n')
    left, source = trainer.available_memory(v2)
    assert left is not None and left > 1_500_000 and 'MemAvailable' in source


def test_volume_cache_is_for_cost_volume_networks_and_in_help(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match='keeps no cost volumes'):
        TrainConfig(arch='ccnn', synthetic=1, volume_cache=str(tmp_path))
    assert '--volume-cache' in build_parser().format_help()
