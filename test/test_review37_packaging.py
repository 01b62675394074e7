"""Review 37: the package installed other ways than the editable dev install (a wheel in another
environment or ``--target``, a colcon install tree, ``torch.hub`` from a checkout)."""

from __future__ import annotations

import ast
import importlib.util
from pathlib import Path
import sys

import pytest

torch = pytest.importorskip('torch')

from cva_confidence_ros.model import weights as weights_module  # noqa: E402
from cva_confidence_ros.model.weights import default_weights_path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = 'cva_confidence_ros'
NAME = 'cvanet_fast_census_bm_d64.pt'


def _share(prefix: Path) -> Path:
    models = prefix / 'share' / PACKAGE / 'models'
    models.mkdir(parents=True)
    (models / NAME).write_bytes(b'stand-in')
    return models / NAME


@pytest.mark.parametrize('layout', ['prefix', 'target'])
def test_weights_of_the_running_install_win_over_those_of_the_interpreters_prefix(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, layout: str
) -> None:
    # A colcon install tree (or a pip --target folder) run through PYTHONPATH with a venv's
    # Python, where an older copy of the package was pip-installed: the venv's weights
    # (<sys.prefix>/share/...) were found first, not those installed with the running code.
    venv = tmp_path / 'venv'
    older = _share(venv)
    if layout == 'prefix':
        install = tmp_path / 'install' / PACKAGE
        site = install / 'lib' / 'python3.12' / 'site-packages'
        own = _share(install)
    else:
        site = tmp_path / 'target'
        own = _share(site)
    monkeypatch.setattr(sys, 'prefix', str(venv))
    monkeypatch.setattr(weights_module, '__file__', str(site / PACKAGE / 'model' / 'weights.py'))
    assert default_weights_path('census_bm', 64, 'cvanet_fast') == own
    # The venv's copy is still a fallback.
    own.unlink()
    assert default_weights_path('census_bm', 64, 'cvanet_fast') == older


def _imported_top_level_modules() -> set[str]:
    found: set[str] = set()
    for source in (ROOT / PACKAGE, ROOT / 'msg_tools'):
        for path in source.rglob('*.py'):
            for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
                if isinstance(node, ast.Import):
                    found.update(alias.name.split('.')[0] for alias in node.names)
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    found.add(node.module.split('.')[0])
    return found


def _hub_dependencies() -> list[str]:
    tree = ast.parse((ROOT / 'hubconf.py').read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(
            isinstance(target, ast.Name) and target.id == 'dependencies'
            for target in node.targets
        ):
            return list(ast.literal_eval(node.value))
    raise AssertionError('hubconf.py has no dependencies list')


def test_hub_dependencies_are_only_modules_the_package_imports() -> None:
    # torch.hub.load refuses to load any entry while one of these is missing: scipy was listed,
    # which nothing imports, so a torch setup without scipy could not load the networks.
    unused = set(_hub_dependencies()) - _imported_top_level_modules()
    assert not unused, f'hubconf.dependencies names modules nothing imports: {sorted(unused)}'


def test_hub_loads_without_scipy(monkeypatch: pytest.MonkeyPatch) -> None:
    find_spec = importlib.util.find_spec

    def without_scipy(name: str, *args: object, **kwargs: object) -> object:
        if name.split('.')[0] == 'scipy':
            return None  # what torch.hub's dependency check sees where scipy is not installed
        return find_spec(name, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(importlib.util, 'find_spec', without_scipy)
    net = torch.hub.load(
        str(ROOT), 'cvanet_fast', source='local', verbose=False, pretrained=False,
        max_disparity=64,
    )
    assert net.meta['arch'] == 'cvanet_fast'
