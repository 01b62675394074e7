"""Review 37 of ``cva-train --volume-cache DIR`` and of the memory check before matching:
a memory limit set on a parent cgroup (a Slurm job's) was missed, every mapped volume kept a
file open (a cache of more scenes than ``ulimit -n`` failed), the temporary file of a writer
killed mid-write stayed forever, and a cache folder shared with a process of the same number
on another machine, or that is a file, was refused or unclearly so.
"""

from __future__ import annotations

import os
from pathlib import Path
import time

import pytest
import torch

from cva_confidence_ros import memory
from cva_confidence_ros.datasets.synthetic import synthetic_pair
from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.training import data, trainer


def _cgroup(folder: Path, limit: str, usage: int, inactive: int = 0, v1: bool = False) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    names = ('memory.limit_in_bytes', 'memory.usage_in_bytes') if v1 else (
        'memory.max', 'memory.current')  # fmt: skip
    (folder / names[0]).write_text(f'{limit}\n')
    (folder / names[1]).write_text(f'{usage}\n')
    key = 'total_inactive_file' if v1 else 'inactive_file'
    (folder / 'memory.stat').write_text(f'{key} {inactive}\n')


def test_a_memory_limit_on_a_parent_cgroup_is_taken(tmp_path: Path, monkeypatch) -> None:
    # cgroup v2 under Slurm: the job's group holds the limit, the task's group reads max.
    root = tmp_path / 'v2'
    job = root / 'system.slice' / 'job_1'
    _cgroup(job, '4000000', 3_000_000, 500_000)
    _cgroup(job / 'step_0', 'max', 2_000_000)
    _cgroup(job / 'step_0' / 'task_0', 'max', 2_000_000)
    proc = tmp_path / 'cgroup'
    proc.write_text('0::/system.slice/job_1/step_0/task_0\n')
    monkeypatch.setattr(memory, '_PROC_CGROUP', proc)
    left, source = trainer.available_memory(root)
    assert left == 1_500_000 and str(job) in source
    # The tightest of the own group's limit and a parent's.
    _cgroup(job / 'step_0' / 'task_0', '8000000', 2_000_000)
    assert trainer.available_memory(root)[0] == 1_500_000
    # cgroup v1 without a namespace: the memory controller's own path below the mount.
    root = tmp_path / 'v1'
    _cgroup(root / 'memory', '9223372036854771712', 5_000_000, v1=True)  # no limit
    _cgroup(root / 'memory' / 'slurm' / 'job_2', '6000000', 5_000_000, 1_000, v1=True)
    proc.write_text('4:memory:/slurm/job_2\n1:cpu,cpuacct:/slurm/job_2\n0::/\n')
    left, source = trainer.available_memory(root)
    assert left == 1_001_000 and 'job_2' in source


def _prepared(cache: data.VolumeCache, count: int) -> list[data.PreparedScene]:
    scenes = []
    for seed in range(count):
        sample = synthetic_pair(seed, 24, 40, 16)
        scenes.append(
            cache.prepare(sample, 'census_bm', 16, trainer._pair_fingerprint(sample))
        )
    return scenes


@pytest.mark.skipif(not Path('/proc/self/fd').is_dir(), reason='needs /proc/self/fd')
def test_mapped_volumes_keep_no_file_open(tmp_path: Path) -> None:
    # numpy's memmap kept one descriptor per volume: with ulimit -n 1024 a cache of about a
    # thousand scenes failed with 'Too many open files', the in-memory run did not.
    _prepared(data.VolumeCache(tmp_path / 'volumes'), 3)  # written
    before = len(os.listdir('/proc/self/fd'))
    scenes = _prepared(data.VolumeCache(tmp_path / 'volumes'), 3)  # read back
    assert len(os.listdir('/proc/self/fd')) == before
    for seed, scene in enumerate(scenes):
        alone = data.prepare_scene(synthetic_pair(seed, 24, 40, 16), 'census_bm', 16)
        assert torch.equal(scene.volume, alone.volume) and scene.factor == alone.factor
    # Copy-on-write: a write to the tensor does not reach the file.
    scenes[0].volume[0, 0, 0] = 7.0
    again = _prepared(data.VolumeCache(tmp_path / 'volumes'), 1)[0]
    assert float(again.volume[0, 0, 0]) != 7.0


def test_temporary_files_of_killed_writers_are_removed(tmp_path: Path) -> None:
    cache = tmp_path / 'volumes'
    cache.mkdir()
    key = 'c240e0e8cd496659254fe6e6c694ec0d-census_bm-d16'
    old = [cache / f'{key}.npy.4242-139871.tmp', cache / f'{key}.labels.npz.4242-139871.tmp']
    fresh = cache / f'{key}.npy.4243-139872.tmp'  # a writer at work now
    other = cache / 'notes.tmp'  # not the cache's
    for path in [*old, fresh, other]:
        path.write_bytes(b'\0' * 1000)
    hours_ago = time.time() - 2 * 3600
    for path in [*old, other]:
        os.utime(path, (hours_ago, hours_ago))
    lines: list[str] = []
    data.VolumeCache(cache, lines.append)
    assert not any(path.exists() for path in old)
    assert fresh.exists() and other.exists()
    assert len(lines) == 1 and 'removed 2 temporary files' in lines[0]


def test_a_probe_removed_by_a_process_of_the_same_number(tmp_path: Path, monkeypatch) -> None:
    # A folder shared between machines: another machine's process of the same number removed
    # the '.probe-<pid>' file first, and the cache was refused as unwritable.
    write = Path.write_bytes

    def written_then_removed(self: Path, content: bytes) -> int:
        count = write(self, content)
        if self.name.startswith('.probe-'):
            self.unlink()
        return count

    monkeypatch.setattr(Path, 'write_bytes', written_then_removed)
    assert data.VolumeCache(tmp_path / 'volumes').folder.is_dir()


def test_a_cache_folder_that_is_a_file_is_said(tmp_path: Path) -> None:
    path = tmp_path / 'volumes'
    path.write_text('x')
    with pytest.raises(ConfigError, match='it is a file, not a folder'):
        data.VolumeCache(path)
