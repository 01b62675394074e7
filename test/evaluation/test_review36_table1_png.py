"""``table1.png`` of a partial run says so, as ``table1.md`` does (the PNG is what goes into
a report)."""

from __future__ import annotations

import pytest
from test_review35_at_scale import D, _middlebury, _restore_threads  # noqa: F401 (fixture)

from cva_confidence_ros.evaluation import table1


@pytest.mark.usefixtures('_restore_threads')
def test_table1_png_of_a_partial_run_says_so(tmp_path, monkeypatch):
    titles: list[str] = []
    original = table1.save_table_png

    def record(records, rows, matchers, path, title, columns=table1.COLUMNS):
        titles.append(title)
        return original(records, rows, matchers, path, title, columns)

    monkeypatch.setattr(table1, 'save_table_png', record)
    root = _middlebury(tmp_path / 'data', 2)
    (root / 'middlebury2014' / 'trainingQ' / 'S1' / 'im1.png').write_bytes(b'not a PNG')
    code = table1.main(['--data-root', str(root), '--matchers', 'census_bm', '--methods',
                        'pkrn', '--max-disparity', str(D), '--max-pixels', '100',
                        '--protocol', 'develop', '--threads', '1',
                        '--out', str(tmp_path / 'out')])
    assert code == 2
    # Before: the Markdown said "Partial: 1 of 2 scenes", the PNG (what goes into a report)
    # looked like a complete table.
    assert titles and 'Partial: 1 of 2 scenes' in titles[0]
    assert (tmp_path / 'out' / 'table1.png').is_file()
