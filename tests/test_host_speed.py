"""testkit.host_speed: the host reference the speed benches print (figures, never asserted against a clock)."""

import pytest

from testkit import host_speed


def test_reference_reports_each_workload_once_per_repeat_as_a_positive_median():
    ref = host_speed.reference(repeats=1)
    assert ref["version"] == host_speed.VERSION and ref["repeats"] == 1
    for key in ("python_ms", "numpy_ms"):
        assert ref[key] > 0
    assert ref["numba_ms"] is None if host_speed.numba is None else ref["numba_ms"] > 0
    text = host_speed.line(ref)
    assert text.startswith(f"host reference v{host_speed.VERSION}") and "python" in text and "numba" in text


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
