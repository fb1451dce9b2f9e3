"""Errors that say how to fix them: the closest known name, and where a load failed.

A misspelled server or registrar name lists the known names with the closest match
(`difflib`); an uncaught `ResourceLoadError` prints the failing load's traceback as its
cause, as `concurrent.futures` prints a worker's, in both placements.
"""

from __future__ import annotations

import pickle
import subprocess
import sys
import textwrap
import traceback
from pathlib import Path

import pytest

import rr_actors as rr


def divide(request: int) -> float:
    return 1 / request  # the line an uncaught error must show


def test_a_misspelled_server_name_suggests_the_closest_known_one(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "camera")
    serve(provider, "filter")

    with pytest.raises(rr.UnknownServerError) as info:
        consumer.call(provider.name, "camra", "x")

    assert (
        f"no resource server '{provider.name}/camra'; did you mean 'camera'? "
        "(known: 'camera', 'filter')"
    ) == str(info.value)


def test_a_server_name_like_no_known_one_lists_the_known_ones(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "camera")

    with pytest.raises(rr.UnknownServerError) as info:
        consumer.fetch_queries(provider.name, "zzz")

    assert f"no resource server '{provider.name}/zzz' (known: 'camera')" == str(info.value)


def test_a_misspelled_registrar_name_suggests_the_closest_known_one(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "camera")
    misspelled = provider.name[:-1] + ("x" if provider.name[-1] != "x" else "y")

    with pytest.raises(rr.UnknownRegistrarError) as info:
        consumer.call(misspelled, "camera", "x")

    message = str(info.value)
    assert message.startswith(f"no registrar named {misspelled!r}")  # (over Zenoh: "on system")
    assert f"; did you mean {provider.name!r}?" in message
    assert f"{consumer.name!r}" in message  # the known names are listed


def test_a_failed_load_carries_its_traceback_as_its_cause(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "divide", divide)

    with pytest.raises(rr.ResourceLoadError) as info:
        consumer.call(provider.name, "divide", 0)

    printed = "".join(traceback.format_exception(info.value))
    assert f'{__file__}", line ' in str(info.value.__cause__)
    assert "in divide" in printed
    assert "return 1 / request  # the line an uncaught error must show" in printed
    assert "The above exception was the direct cause of the following exception" in printed


def test_the_cause_survives_pickling(make_registrar, serve):
    provider, consumer = make_registrar("provider"), make_registrar("consumer")
    serve(provider, "divide", divide)
    with pytest.raises(rr.ResourceLoadError) as info:
        consumer.call(provider.name, "divide", 0)

    copy = pickle.loads(pickle.dumps(info.value))

    assert copy.__cause__ is not None
    assert (str(info.value), str(info.value.__cause__)) == (str(copy), str(copy.__cause__))


def test_an_uncaught_load_error_prints_the_file_and_line_of_the_failing_load(
    tmp_path: Path,
) -> None:
    script = tmp_path / "broken.py"
    script.write_text(
        textwrap.dedent(
            """
            import rr_actors as rr

            def broken(request):
                return 1 / 0

            erm = rr.ResourceRegistrar.start("erm")
            app = rr.ResourceRegistrar.start("app")
            try:
                erm.register_server("broken", load=broken, unload=lambda q, r: None)
                app.call("erm", "broken", {})
            finally:
                app.stop()
                erm.stop()
            """
        )
    )

    result = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=60, check=False
    )

    assert 1 == result.returncode
    assert f'File "{script}", line 5, in broken' in result.stderr
    assert result.stderr.rstrip().endswith(
        "rr_actors.errors.ResourceLoadError: ZeroDivisionError: division by zero (at erm/broken)"
    )
