"""Exit statuses and stderr of the console scripts as shell scripts, CI jobs and Slurm see them:
130 on Ctrl-C and 143 on SIGTERM with one line (no traceback, no silent -15), a quiet 141 for
a stdout whose reader went away (``| head -1``), and the codes in every tool's ``--help``.

The signal and pipe cases run in subprocesses (a SIGTERM's default action would end the test
runner; a closed stdout is a real pipe's), with the slow parts of the tools replaced."""

from __future__ import annotations

from collections.abc import Callable
import json
import os
from pathlib import Path
import signal
import subprocess
import sys
import textwrap

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _env() -> dict[str, str]:
    return {**os.environ, 'PYTHONPATH': os.pathsep.join(
        [str(ROOT), *filter(None, [os.environ.get('PYTHONPATH')])])}


def _with_closed_stdout(code: str) -> subprocess.CompletedProcess[str]:
    """Run ``code`` with a stdout pipe whose reader is gone, as after ``| head -1``."""
    read, write = os.pipe()
    os.close(read)
    try:
        return subprocess.run([sys.executable, '-c', textwrap.dedent(code)], stdout=write,
                              stderr=subprocess.PIPE, text=True, env=_env(), timeout=120,
                              check=False)
    finally:
        os.close(write)


def _signalled(code: str, signum: int, marker: str) -> tuple[int, str]:
    """Run ``code``, send ``signum`` once ``marker`` is on its stderr; (status, stderr)."""
    process = subprocess.Popen([sys.executable, '-c', textwrap.dedent(code)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env=_env())
    assert process.stderr is not None
    lines = []
    for line in process.stderr:
        lines.append(line)
        if marker in line:
            process.send_signal(signum)
            break
    out, err = process.communicate(timeout=120)
    return process.returncode, ''.join(lines) + err


# cva-benchmark with its measurement replaced: a worker that takes long, a table of 100 kB.
_BENCHMARK = """
    import sys, time
    from cva_confidence_ros import benchmark

    def measure(name, settings, *extra):
        {measure}
    benchmark._run_in_subprocess = measure
    benchmark.format_table = lambda records, threads: 'row\\n' * 25000
    sys.exit(benchmark.main(['--width', '64', '--height', '48', '--max-disparity', '32',
                             '--matchers', 'census_bm', '--no-network'{extra}]))
"""


def test_benchmark_with_a_closed_stdout_exits_141_without_a_traceback(tmp_path: Path) -> None:
    # `cva-benchmark … | head -1` printed a BrokenPipeError traceback and exited 1.
    out = tmp_path / 'records.json'
    result = _with_closed_stdout(_BENCHMARK.format(
        measure="return {'config': name}", extra=f", '--json', {str(out)!r}"))
    assert result.returncode == 141, result.stderr
    assert 'Traceback' not in result.stderr and 'BrokenPipe' not in result.stderr
    assert out.is_file()  # written before the table


@pytest.mark.parametrize(('signum', 'status', 'line'), [
    (signal.SIGTERM, 143, 'cva-benchmark: terminated'),
    (signal.SIGINT, 130, 'cva-benchmark: interrupted'),
])
def test_benchmark_ends_on_a_signal_with_one_line_and_its_status(
    signum: int, status: int, line: str
) -> None:
    # SIGTERM (a CI job's time limit) ended it without a word (-15); Ctrl-C printed a
    # KeyboardInterrupt traceback.
    code, err = _signalled(_BENCHMARK.format(measure='time.sleep(30)', extra=''), signum,
                           'measuring census_bm')
    assert code == status, err
    assert err.splitlines()[-1] == line
    assert 'Traceback' not in err


def test_demo_stopped_by_sigterm_in_step_1_exits_143_with_one_line(tmp_path: Path) -> None:
    # Step 1 answered Ctrl-C with 130, but SIGTERM ended it without a word.
    code, err = _signalled(f"""
        import sys, time
        from cva_confidence_ros import demo

        def match_all(*args, **kwargs):
            print('matching', file=sys.stderr, flush=True)
            time.sleep(30)
        demo._match_all = match_all
        sys.exit(demo.main(['--out', {str(tmp_path / 'demo')!r}, '--matchers', 'census_bm',
                            '--methods', 'pkrn']))
    """, signal.SIGTERM, 'matching')
    assert code == 143, err
    assert err.splitlines()[-1] == 'cva-demo: stopped by SIGTERM in step 1'


def test_evaluation_tools_with_a_closed_stdout_exit_141_quietly() -> None:
    # cva-evaluate / cva-table1 said 'error: [Errno 32] Broken pipe' and exited 1, the code
    # of an unexpected failure, after writing everything.
    result = _with_closed_stdout("""
        import sys
        from cva_confidence_ros.evaluation.cli import exit_code

        def table():
            sys.stdout.write('| row |\\n' * 20000)
            sys.stdout.flush()
            return 0
        sys.exit(exit_code('cva-evaluate', table))
    """)
    assert result.returncode == 141
    assert result.stderr == ''


def _help(main: Callable[[list[str]], int], capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit) as ended:
        main(['--help'])
    assert ended.value.code == 0
    return ' '.join(capsys.readouterr().out.split())


def test_every_tool_with_codes_names_them_in_its_help(
    capsys: pytest.CaptureFixture[str],
) -> None:
    # cva-evaluate's 2 for a partial run, cva-param's 1 for a refusal and 130 / 143 were in
    # the README only.
    from cva_confidence_ros import benchmark, demo
    from cva_confidence_ros.evaluation import cli, table1
    from cva_confidence_ros.ros import lifecycle_cli, param_cli

    for main in (cli.main, table1.main, benchmark.main, demo.main):
        text = _help(main, capsys)
        assert 'Exit codes: 0 done, 2 bad input' in text
        assert '130 stopped by Ctrl-C, 143 by SIGTERM' in text
    assert 'partial run' in _help(cli.main, capsys)
    assert 'partial table' in _help(table1.main, capsys)
    assert '1 the node refused the value' in _help(param_cli.main, capsys)
    assert '1 the node refused the transition' in _help(lifecycle_cli.main, capsys)
    for main in (param_cli.main, lifecycle_cli.main):
        assert '130 stopped by Ctrl-C, 143 by SIGTERM' in _help(main, capsys)


def test_a_broken_pipe_other_than_stdout_is_not_swallowed(monkeypatch: pytest.MonkeyPatch) -> None:
    # Only a closed stdout ends quietly with 141: a subprocess's or a socket's broken pipe
    # (the node suite talks to a node process) is a failure to show.
    from cva_confidence_ros import benchmark

    def broken(_argv: object) -> int:
        raise BrokenPipeError(32, 'Broken pipe')

    monkeypatch.setattr(benchmark, '_main', broken)
    with pytest.raises(BrokenPipeError):
        benchmark.main([])

def _signalled_term(code: str, marker: str) -> tuple[int, str]:
    return _signalled(code, signal.SIGTERM, marker)


# Follow-ups (once the contract above was in place): the node suite, cva-export, the bag
# tools while loading, the evaluation tools' word for SIGTERM.


def test_node_suite_writes_its_json_before_the_table(tmp_path: Path) -> None:
    # The table was printed first: `cva-benchmark --suite node --json X | head -1` ended with
    # 141 and no X, the run's minutes lost.
    out = tmp_path / 'node.json'
    result = _with_closed_stdout(f"""
        import sys
        from cva_confidence_ros import benchmark, node_benchmark

        node_benchmark.run_suite = lambda settings, matchers, methods: [{{'config': 'x'}}]
        node_benchmark.format_table = lambda records, threads: 'row\\n' * 25000
        sys.exit(benchmark.main(['--suite', 'node', '--json', {str(out)!r}]))
    """)
    assert result.returncode == 141, result.stderr
    assert 'Traceback' not in result.stderr
    assert json.loads(out.read_text())[0]['config'] == 'x'


def test_node_suite_refuses_a_json_folder_before_measuring(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # A --json that names a folder was found only after every node had run: IsADirectoryError,
    # a traceback and exit 1.
    from cva_confidence_ros import benchmark, node_benchmark

    ran = []
    monkeypatch.setattr(node_benchmark, 'run_suite', lambda *args: ran.append(args) or [])
    with pytest.raises(SystemExit) as ended:
        benchmark.main(['--suite', 'node', '--json', str(tmp_path)])
    assert ended.value.code == 2
    assert not ran
    err = capsys.readouterr().err
    assert err.startswith('cva-benchmark --suite node: error: --json') and err.count('\n') == 1


def test_node_suite_on_its_own_says_one_line_on_sigterm() -> None:
    # node_benchmark.main called on its own (not under cva-benchmark's handler): SIGTERM ended
    # it with 143 and not a word.
    code, err = _signalled_term("""
        import sys, time
        from cva_confidence_ros import node_benchmark

        def run_suite(settings, matchers, methods):
            with node_benchmark._stop_on_sigterm():
                print('measuring', file=sys.stderr, flush=True)
                time.sleep(30)
        node_benchmark.run_suite = run_suite
        sys.exit(node_benchmark.main([]))
    """, 'measuring')
    assert code == 143, err
    assert err.splitlines()[-1] == 'cva-benchmark --suite node: terminated'


@pytest.mark.parametrize('suite', ['fast', 'gpu', 'cloud', 'node'])
def test_every_benchmark_suite_names_the_exit_codes_in_its_help(
    suite: str, capsys: pytest.CaptureFixture[str]
) -> None:
    # Only the matcher suite's --help had the epilog.
    from cva_confidence_ros import benchmark

    with pytest.raises(SystemExit) as ended:
        benchmark.main(['--suite', suite, '--help'])
    assert ended.value.code == 0
    text = ' '.join(capsys.readouterr().out.split())
    assert ' '.join(benchmark.EXIT_CODES.split()) in text


def test_export_replaces_its_own_earlier_export_only(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The card replaced any .json beside --out without a word (a cva-evaluate --json named
    # like the graph); an earlier export is still replaced, as the README promises.
    from cva_confidence_ros.model.export import main

    out = tmp_path / 'census_bm.onnx'
    results = tmp_path / 'census_bm.json'
    results.write_text('{"records": []}\n')
    assert main(['--out', str(out), '--no-check']) == 2
    err = capsys.readouterr().err
    assert err.startswith('cva-export: error: the card beside --out') and '--overwrite' in err
    assert err.count('\n') == 1
    assert results.read_text() == '{"records": []}\n' and not out.exists()
    assert main(['--out', str(out), '--no-check', '--overwrite']) == 0
    assert json.loads(results.read_text())['arch'] == 'cvanet_fast'
    out.write_bytes(b'older graph')
    assert main(['--out', str(out), '--no-check']) == 0  # an earlier export: replaced
    assert out.read_bytes() != b'older graph'
    results.write_text('not json')
    assert main(['--out', str(out), '--no-check']) == 2
    assert 'not a card of cva-export' in capsys.readouterr().err
    assert results.read_text() == 'not json'
    with pytest.raises(SystemExit):
        main(['--help'])
    assert '130 stopped by Ctrl-C, 143 by SIGTERM' in ' '.join(capsys.readouterr().out.split())


def test_export_says_terminated_on_sigterm(tmp_path: Path) -> None:
    # It said 'cva-export: interrupted' (as for Ctrl-C) and exited 143.
    code, err = _signalled_term(f"""
        import sys, time
        from cva_confidence_ros.model import export

        def export_onnx(*args, **kwargs):
            print('exporting', file=sys.stderr, flush=True)
            time.sleep(30)
        export.export_onnx = export_onnx
        sys.exit(export.main(['--out', {str(tmp_path / 'x.onnx')!r}, '--no-check']))
    """, 'exporting')
    assert code == 143, err
    assert err.splitlines()[-1] == 'cva-export: terminated'


def test_bag_from_dataset_sigterm_while_loading_says_one_line(tmp_path: Path) -> None:
    # Before write_dataset_bag set its handlers (the data set still loading), SIGTERM took its
    # default action: 143 without a word.
    code, err = _signalled_term(f"""
        import sys, time
        from cva_confidence_ros import datasets
        from msg_tools import bag_from_dataset

        def load_dataset(*args, **kwargs):
            print('loading', file=sys.stderr, flush=True)
            time.sleep(30)
        datasets.load_dataset = load_dataset
        sys.exit(bag_from_dataset.main(['--dataset', 'motorcycle', '--out',
                                        {str(tmp_path / 'bag')!r}]))
    """, 'loading')
    assert code == 143, err
    assert err.splitlines()[-1] == 'cva-bag-from-dataset: terminated before the bag was created'
    assert not (tmp_path / 'bag').exists()


def test_evaluation_tools_say_terminated_on_sigterm(capsys: pytest.CaptureFixture[str]) -> None:
    # cva-evaluate and cva-table1 exited 143 on SIGTERM but said 'interrupted', as for Ctrl-C.
    from cva_confidence_ros.evaluation.cli import exit_code

    def killed() -> int:
        signal.raise_signal(signal.SIGTERM)
        return 0

    assert exit_code('cva-evaluate', killed) == 143
    assert capsys.readouterr().err.splitlines() == ['cva-evaluate: terminated']
