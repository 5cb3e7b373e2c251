"""testkit.host_speed: the host reference the speed benches print (figures, never asserted against a clock)."""

import pytest

from testkit import host_speed


def test_reference_reports_each_workload_once_per_repeat_as_a_positive_median():
    ref = host_speed.reference(repeats=1)
    assert ref["version"] == host_speed.VERSION and ref["repeats"] == 1
    for key in ("python_ms", "numpy_ms"):
        assert ref[key] > 0
    for key in ("numba_ms", "numba_2t_ms"):
        assert ref[key] is None if host_speed.numba is None else ref[key] > 0
    text = host_speed.line(ref)
    assert text.startswith(f"host reference v{host_speed.VERSION}") and "python" in text and "numba" in text
    assert "two threads at once" in text


def test_the_workloads_are_fixed_work_not_random_each_call():
    # the same numbers every call: a change of figures is the host's, not the workload's
    assert host_speed._python_work() == host_speed._python_work()
    a, b = host_speed._numpy_inputs(), host_speed._numpy_inputs()
    assert all((x == y).all() for x, y in zip(a, b))
    assert host_speed._numpy_work(a) == host_speed._numpy_work(b)


def test_cli_refuses_zero_repeats(capsys):
    with pytest.raises(SystemExit) as err:
        host_speed.main(["--repeats", "0"])
    assert err.value.code == 2
    assert "--repeats must be >= 1" in capsys.readouterr().err


@pytest.mark.skipif(host_speed.numba is None, reason="numba does not import here")
def test_two_at_once_does_the_single_scatter_on_each_thread_into_its_own_copy():
    table, rows, weights, src = host_speed._numba_inputs()
    rows, weights = rows[:5000], weights[:5000]
    expected = table.copy()
    host_speed._scatter_rows(expected, rows, weights, src)
    before = table.copy()
    tables = host_speed._two_at_once(table, rows, weights, src)
    assert len(tables) == 2 and all((t == expected).all() for t in tables)
    assert (table == before).all()  # the caller's table is left alone
