"""The tests that share a fixture computed once per module run on one xdist worker
(tests/conftest.py marks them with ``xdist_group`` and makes sure the group reaches
pytest-xdist's scheduler): else each worker computes the fixture again."""

import pytest


@pytest.fixture(scope="module")
def per_module():
    return object()


@pytest.fixture(scope="session")
def session_of_this_module():
    return object()


def _under_loadgroup(request) -> None:
    if not hasattr(request.config, "workerinput") or not request.config.getvalue("loadgroup"):
        pytest.skip("checks the default run's pytest-xdist scheduling (-n auto --dist loadgroup)")


def test_a_module_fixtures_tests_are_one_group(per_module, request):
    _under_loadgroup(request)
    assert request.node.nodeid.endswith("@" + request.module.__name__), request.node.nodeid


def test_a_session_fixture_of_the_module_groups_its_tests_too(session_of_this_module, request):
    _under_loadgroup(request)
    assert request.node.nodeid.endswith("@" + request.module.__name__), request.node.nodeid


def test_a_test_without_such_a_fixture_goes_anywhere(request):
    _under_loadgroup(request)
    assert "@" not in request.node.nodeid, request.node.nodeid
