"""A writable folder for numba's kernel cache, found before any kernel is defined.

The package's numba kernels are compiled with ``cache=True``; with no writable cache folder
numba refuses to define them (``RuntimeError: cannot cache function ...``), so this runs when
the package is imported (and again in the node's entry point, which says so and exits 2 when
there is none at all).
"""

from __future__ import annotations

from functools import cache
import os
from pathlib import Path
import stat
import sys
import tempfile

from cva_confidence_ros.errors import ConfigError

__all__ = ['ensure_jit_cache', 'start_numba_threads']


def ensure_jit_cache() -> str | None:
    """Give numba's kernel cache a writable folder when the installed package's is not.

    The matchers' and networks' numba kernels are compiled with ``cache=True``: numba keeps them
    in ``__pycache__`` beside the source, else in ``$XDG_CACHE_HOME/numba`` (``~/.cache``), and
    with neither writable (a root-owned or read-only install run by another user, no writable
    home) it refuses to define the kernel: importing the node failed with ``RuntimeError:
    cannot cache function …``. Then ``NUMBA_CACHE_DIR`` is set to a folder of this user's in
    the temporary folder (kept between runs as long as that is). A ``NUMBA_CACHE_DIR`` already
    set is left as it is. Call it before the kernels' modules are imported.

    Returns:
        The folder set, or None when numba's own choice works (or was set by the user).

    Raises:
        ConfigError: No writable folder for the cache either; names ``NUMBA_CACHE_DIR``.
    """
    if os.environ.get('NUMBA_CACHE_DIR'):
        return None
    package = Path(__file__).resolve().parent  # cva_confidence_ros
    packages = [package, *(path.parent for path in sorted(package.glob('*/__init__.py')))]
    if all(_writable_folder(path / '__pycache__') for path in packages):
        return None
    user_cache = os.environ.get('XDG_CACHE_HOME') or os.path.expanduser('~/.cache')
    if _writable_folder(Path(user_cache) / 'numba'):
        return None
    try:
        folder = os.path.join(tempfile.gettempdir(), f'cva_confidence_ros-numba-{os.getuid()}')
        os.makedirs(folder, mode=0o700, exist_ok=True)
        info = os.lstat(folder)
        # numba's cache files are pickles: never load them from a folder others can write to.
        if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid() or info.st_mode & 0o022:
            folder = tempfile.mkdtemp(prefix='cva_confidence_ros-numba-')
    except OSError:
        folder = ''
    if not folder or not _writable_folder(Path(folder)):
        raise ConfigError(
            f'no writable folder for the compiled numba kernels: not the package ({package}), '
            f'not {user_cache}/numba, not the temporary folder; set NUMBA_CACHE_DIR to one'
        )
    os.environ['NUMBA_CACHE_DIR'] = folder
    numba_config = sys.modules.get('numba.core.config')
    if numba_config is not None:  # numba read its environment when imported
        numba_config.CACHE_DIR = folder  # type: ignore[attr-defined]
    return folder


def _writable_folder(path: Path) -> bool:
    """Whether ``path`` exists or can be made, and a file can be written in it (numba's test)."""
    try:
        path.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=path).close()
    except OSError:
        return False
    return True


@cache
def start_numba_threads() -> str:
    """Start numba's threading layer as the first parallel kernel would, keeping torch's
    thread count; the layer's name (chosen once per process, fixed from then on).

    numba's OpenMP layer sets OpenMP's thread count to its own as it starts, in the libgomp
    that torch uses too: a user's ``torch.set_num_threads(1)`` read 2 after the first frame
    (and torch ran on 2 threads). Called before the package's first parallel kernel (a
    pipeline's first frame, :func:`cva_confidence_ros.matching.compute_cost_volume`).
    """
    import numba
    from numba.np.ufunc import parallel

    torch = sys.modules.get('torch')
    threads = torch.get_num_threads() if torch is not None else None
    parallel._launch_threads()
    if torch is not None and torch.get_num_threads() != threads:
        torch.set_num_threads(threads)
    return str(numba.threading_layer())
