"""Shared fixtures: fresh databases on the local PostgreSQL / MariaDB / Redis servers, and
Pendulum experts for the imitation learners (trained once per session).

Tests that need a server are marked ``services``. When the server cannot be reached they are
skipped with the reason, unless ``ERMRL_REQUIRE_SERVICES=1`` (CI), where they fail instead.
Server addresses can be changed with ``ERMRL_TEST_POSTGRES``, ``ERMRL_TEST_MYSQL`` and
``ERMRL_TEST_REDIS`` (admin URLs; each test gets its own database or key prefix).
"""

from __future__ import annotations

import os
import tempfile
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import urlsplit, urlunsplit

import pytest

import ermrl  # noqa: F401  (first: pins numpy's BLAS kernel before a test module loads numpy)

POSTGRES_ADMIN = os.environ.get("ERMRL_TEST_POSTGRES", "postgresql://postgres@127.0.0.1:5432/test")
MYSQL_ADMIN = os.environ.get("ERMRL_TEST_MYSQL", "mysql+pymysql://root@127.0.0.1:3306/test")
REDIS_URL = os.environ.get("ERMRL_TEST_REDIS", "redis://127.0.0.1:6379/0")


def services_required() -> bool:
    """Whether a missing server is an error (CI sets ``ERMRL_REQUIRE_SERVICES=1``)."""
    return os.environ.get("ERMRL_REQUIRE_SERVICES", "") == "1"


def unavailable(reason: str) -> None:
    """Skip the test, or fail it when services are required."""
    if services_required():
        pytest.fail(f"{reason} (ERMRL_REQUIRE_SERVICES=1: not skipping)", pytrace=False)
    pytest.skip(reason)


def _with_database(url: str, name: str) -> str:
    parts = urlsplit(url)
    return urlunsplit(parts._replace(path=f"/{name}"))


# Exists while a test (tests/test_storage_restart.py) has the PostgreSQL server stopped: the
# tests beside it, in other xdist workers, wait for it to be back before they connect.
POSTGRES_RESTART_MARK = Path(tempfile.gettempdir()) / "ermrl-test-postgres-restart"


def wait_for_postgres_restart(limit: float = 60.0) -> None:
    """Wait (up to ``limit`` s) while another test restarts the PostgreSQL server."""
    deadline = time.monotonic() + limit
    while POSTGRES_RESTART_MARK.exists() and time.monotonic() < deadline:
        time.sleep(0.2)


@pytest.fixture
def postgres_url() -> Iterator[str]:
    """A fresh, empty PostgreSQL database (dropped after the test)."""
    wait_for_postgres_restart()
    try:
        import psycopg2

        admin = psycopg2.connect(POSTGRES_ADMIN, connect_timeout=3)
    except Exception as err:  # driver missing or server down
        unavailable(f"PostgreSQL unreachable at {POSTGRES_ADMIN}: {str(err).strip()}")
    admin.autocommit = True
    name = f"ermrl_test_{uuid.uuid4().hex[:12]}"
    with admin.cursor() as cur:
        cur.execute(f"CREATE DATABASE {name}")
    admin.close()
    try:
        yield _with_database(POSTGRES_ADMIN, name)
    finally:
        # A connection of its own: a test may have restarted the server meanwhile.
        wait_for_postgres_restart()
        admin = psycopg2.connect(POSTGRES_ADMIN, connect_timeout=10)
        admin.autocommit = True
        with admin.cursor() as cur:
            cur.execute(f"DROP DATABASE IF EXISTS {name} WITH (FORCE)")
        admin.close()


@pytest.fixture
def mysql_url() -> Iterator[str]:
    """A fresh, empty MySQL/MariaDB database (dropped after the test)."""
    parts = urlsplit(MYSQL_ADMIN)
    try:
        import pymysql

        admin = pymysql.connect(
            host=parts.hostname or "127.0.0.1",
            port=parts.port or 3306,
            user=parts.username or "root",
            password=parts.password or "",
            connect_timeout=3,
            autocommit=True,
        )
    except Exception as err:
        unavailable(f"MySQL/MariaDB unreachable at {MYSQL_ADMIN}: {str(err).strip()}")
    name = f"ermrl_test_{uuid.uuid4().hex[:12]}"
    with admin.cursor() as cur:
        cur.execute(f"CREATE DATABASE {name}")
    try:
        yield _with_database(MYSQL_ADMIN, name)
    finally:
        with admin.cursor() as cur:
            cur.execute(f"DROP DATABASE IF EXISTS {name}")
        admin.close()


@pytest.fixture
def redis_url() -> Iterator[str]:
    """A Redis journal URL with a fresh key prefix (its keys are deleted after the test)."""
    try:
        import redis

        client = redis.Redis.from_url(REDIS_URL, socket_connect_timeout=3)
        client.ping()
    except Exception as err:
        unavailable(f"Redis unreachable at {REDIS_URL}: {str(err).strip()}")
    prefix = f"ermrl_test_{uuid.uuid4().hex[:12]}"
    try:
        yield f"{REDIS_URL}?prefix={prefix}"
    finally:
        for key in client.scan_iter(f"{prefix}:*"):
            client.delete(key)
        client.close()


@pytest.fixture
def fresh_storage(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """A fresh storage URL of the kind given by indirect parametrization.

    ``sqlite``, ``journal`` (file), ``postgresql``, ``mysql`` or ``redis``; mark the server
    kinds with ``pytest.mark.services``.
    """
    kind = getattr(request, "param", "sqlite")
    if kind == "sqlite":
        return f"sqlite:///{tmp_path}/study.db"
    if kind == "journal":
        return f"journal:///{tmp_path}/study.log"
    if kind == "postgresql":
        return request.getfixturevalue("postgres_url")
    if kind == "mysql":
        return request.getfixturevalue("mysql_url")
    if kind == "redis":
        return request.getfixturevalue("redis_url")
    raise ValueError(f"unknown storage kind {kind!r}")


# -- experts for the imitation learners (bc, dagger, imitation-sac) --------------------------------


@pytest.fixture(scope="session")
def tiny_expert(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A SAC Pendulum expert of 300 steps (quality irrelevant: its actions vary with the state)."""
    from ermrl.experts import train_expert

    out = tmp_path_factory.mktemp("experts") / "pendulum"
    train_expert(
        "Pendulum-v1",
        "sac",
        300,
        out,
        seed=0,
        overrides={"learning_starts": 100},
        n_eval_episodes=1,
    )
    return out


@pytest.fixture(scope="session")
def good_expert(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A SAC Pendulum expert of 5000 steps (about -160: it swings up); for slow tests."""
    from ermrl.experts import train_expert

    out = tmp_path_factory.mktemp("experts") / "pendulum-good"
    train_expert("Pendulum-v1", "sac", 5000, out, seed=0, n_eval_episodes=2)
    return out


# The per-test limit (pytest-timeout) is `timeout` in pyproject.toml for the default suite; a
# slow end-to-end test, whose subprocesses have their own limits of up to 25 min, gets this one
# unless it sets its own.
SLOW_TEST_TIMEOUT_S = 1800


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if item.get_closest_marker("slow") and not item.get_closest_marker("timeout"):
            item.add_marker(pytest.mark.timeout(SLOW_TEST_TIMEOUT_S))
