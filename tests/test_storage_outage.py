"""Storage servers that do not answer: connecting is bounded in time and fails in one line, and a
worker rides out a short outage by retrying its storage calls."""

from __future__ import annotations

import contextlib
import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from urllib.parse import urlsplit, urlunsplit

import optuna
import pytest
import sqlalchemy
from optuna.trial import TrialState

import ermrl.storage._locks as locks_module
import ermrl.storage._url as url_module
from ermrl.storage import StorageError, open_storage, storage_lock


@pytest.fixture
def silent_port() -> Iterator[int]:
    """A port whose listener accepts connections (the kernel does) but never says a word."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(16)
    try:
        yield listener.getsockname()[1]
    finally:
        listener.close()


@pytest.mark.timeout(20)  # it hung for good before
@pytest.mark.parametrize("scheme", ["mysql", "mysql+pymysql", "postgresql", "redis"])
def test_a_server_that_never_greets_fails_in_one_line(
    silent_port: int, scheme: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """PyMySQL waited for the greeting without a limit (over 100 s against a silent listener,
    61 s against PostgreSQL's port) and Redis for 252 s (its client waits the retry window for
    each answer); now the connect timeout covers it (10 s, 1 s here)."""
    monkeypatch.setattr(url_module, "CONNECT_TIMEOUT_S", 1.0)
    start = time.monotonic()
    with pytest.raises(StorageError) as caught:
        open_storage(f"{scheme}://root@127.0.0.1:{silent_port}/test", mode="read")
    assert time.monotonic() - start < 5
    assert "\n" not in str(caught.value) and "cannot open storage" in str(caught.value)


def test_only_connecting_is_bounded_on_mysql(
    mysql_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The handshake's timeout is lifted once connected: a query may take longer."""
    monkeypatch.setattr(url_module, "CONNECT_TIMEOUT_S", 1.0)
    storage = open_storage(mysql_url)
    with storage.engine.connect() as connection:  # type: ignore[attr-defined]
        assert connection.execute(sqlalchemy.text("SELECT SLEEP(1.5)")).scalar() == 0


class TcpProxy:
    """A TCP proxy to a server, which the test stops (its port refuses, its connections drop)
    and starts again on the same port: a server restart, without touching the real server
    (other processes use it)."""

    def __init__(self, port: int) -> None:
        self.target = ("127.0.0.1", port)
        self._sockets: list[socket.socket] = []
        self._lock = threading.Lock()
        probe = socket.socket()
        probe.bind(("127.0.0.1", 0))
        self.port = probe.getsockname()[1]
        probe.close()
        self._listener: socket.socket | None = None
        self.start()

    def start(self) -> None:
        listener = socket.socket()
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", self.port))
        listener.listen(64)
        self._listener = listener
        threading.Thread(target=self._accept, args=(listener,), daemon=True).start()

    def stop(self) -> None:
        with self._lock:
            if self._listener is not None:  # shutdown wakes the thread blocked in accept()
                with contextlib.suppress(OSError):
                    self._listener.shutdown(socket.SHUT_RDWR)
                self._listener.close()
                self._listener = None
            for sock in self._sockets:
                with contextlib.suppress(OSError):
                    sock.shutdown(socket.SHUT_RDWR)
                sock.close()
            self._sockets.clear()

    def _accept(self, listener: socket.socket) -> None:
        while True:
            try:
                client, _ = listener.accept()
            except OSError:
                return  # stopped
            try:
                server = socket.create_connection(self.target, timeout=5)
            except OSError:
                client.close()
                continue
            server.settimeout(None)
            with self._lock:
                self._sockets += [client, server]
            for a, b in ((client, server), (server, client)):
                threading.Thread(target=self._pipe, args=(a, b), daemon=True).start()

    @staticmethod
    def _pipe(source: socket.socket, sink: socket.socket) -> None:
        with contextlib.suppress(OSError):
            while data := source.recv(65536):
                sink.sendall(data)
        with contextlib.suppress(OSError):
            sink.shutdown(socket.SHUT_WR)


@pytest.fixture
def outage() -> Iterator[Callable[[TcpProxy, float], threading.Thread]]:
    """Stop a proxy for some seconds, in the background."""
    threads: list[threading.Thread] = []

    def run(proxy: TcpProxy, seconds: float) -> threading.Thread:
        def down() -> None:
            proxy.stop()
            time.sleep(seconds)
            proxy.start()

        thread = threading.Thread(target=down, daemon=True)
        thread.start()
        threads.append(thread)
        return thread

    yield run
    for thread in threads:
        thread.join()


def _through(url: str, proxy: TcpProxy) -> str:
    parts = urlsplit(url)
    return urlunsplit(
        parts._replace(netloc=parts.netloc.replace(f":{proxy.target[1]}", f":{proxy.port}"))
    )


@pytest.mark.timeout(60)
@pytest.mark.parametrize("kind", ["postgres", "redis"])
def test_a_worker_rides_out_a_short_outage(
    kind: str,
    request: pytest.FixtureRequest,
    outage: Callable[[TcpProxy, float], threading.Thread],
    caplog: pytest.LogCaptureFixture,
) -> None:
    """The server goes away for 1.5 s mid-run (refused, connections dropped): the worker's
    storage calls are retried and every trial completes; they died at once before."""
    url = request.getfixturevalue(f"{kind}_url")
    proxy = TcpProxy(urlsplit(url).port or (5432 if kind == "postgres" else 6379))
    try:
        storage = open_storage(_through(url, proxy), retry_window=30)
        study = optuna.create_study(study_name="s", storage=storage)
        study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=2)
        with caplog.at_level("WARNING", logger="ermrl.storage"):
            outage(proxy, 1.5).join(0.2)
            study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=3)
        trials = study.get_trials()
        assert [t.state for t in trials] == [TrialState.COMPLETE] * 5
        assert "unreachable" in caplog.text and "reachable again" in caplog.text
    finally:
        proxy.stop()


@pytest.mark.timeout(60)
def test_a_worker_gives_up_after_the_retry_window_in_one_line(
    postgres_url: str, outage: Callable[[TcpProxy, float], threading.Thread]
) -> None:
    proxy = TcpProxy(urlsplit(postgres_url).port or 5432)
    try:
        study = optuna.create_study(
            study_name="s", storage=open_storage(_through(postgres_url, proxy), retry_window=1)
        )
        outage(proxy, 4)
        time.sleep(0.2)
        start = time.monotonic()
        with pytest.raises(StorageError) as caught:
            study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=1)
        assert 0.9 < time.monotonic() - start < 3.5
        message = str(caught.value)
        assert "\n" not in message and "unreachable for 1 s" in message
        assert "ERMRL_STORAGE_RETRY_S" in message
    finally:
        proxy.stop()


@pytest.mark.timeout(60)
def test_a_paused_redis_holds_the_calls_and_no_record_is_sent_twice(redis_url: str) -> None:
    """``CLIENT PAUSE``: the server holds every command for 3 s, then runs it; the worker waits
    (its answer timeout follows the retry window) instead of timing out and sending it again."""
    import redis

    base, _, prefix = redis_url.partition("?prefix=")
    admin = redis.Redis.from_url(base)

    def n_records() -> int:
        return int(admin.get(f"{prefix}:log_number")) + 1

    study = optuna.create_study(study_name="s", storage=open_storage(redis_url, retry_window=30))
    created = n_records()
    study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=1)
    per_trial = n_records() - created
    admin.execute_command("CLIENT", "PAUSE", 3000, "WRITE")
    start = time.monotonic()
    study.optimize(lambda t: t.suggest_float("x", 0, 1), n_trials=1)
    assert time.monotonic() - start > 2
    assert [t.state for t in study.get_trials()] == [TrialState.COMPLETE] * 2
    assert n_records() == created + 2 * per_trial  # no record sent twice


@pytest.mark.parametrize("value", ["soon", "-1", "inf"])
def test_a_bad_retry_window_is_one_line(value: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ERMRL_STORAGE_RETRY_S", value)
    with pytest.raises(StorageError, match="ERMRL_STORAGE_RETRY_S|retry window"):
        open_storage("postgresql://nobody@127.0.0.1:1/none")


# -- the claim lock of a server storage -----------------------------------------------------------


def _advisory_holders(admin: object, url: str) -> list[int]:
    """The server processes that hold an advisory lock in the database of ``url``."""
    with admin.cursor() as cur:  # type: ignore[attr-defined]
        cur.execute(
            "SELECT pid FROM pg_locks l JOIN pg_database d ON d.oid = l.database "
            "WHERE l.locktype = 'advisory' AND l.granted AND d.datname = %s",
            (urlsplit(url).path.lstrip("/"),),
        )
        return [row[0] for row in cur.fetchall()]


@pytest.fixture
def pg_admin(postgres_url: str) -> Iterator[object]:
    import psycopg2

    admin = psycopg2.connect(postgres_url)
    admin.autocommit = True
    try:
        yield admin
    finally:
        admin.close()


@pytest.mark.timeout(60)
def test_a_lock_whose_connection_died_is_released_without_an_error(
    postgres_url: str, pg_admin: object, caplog: pytest.LogCaptureFixture
) -> None:
    """A server restart drops the connection that holds the claim lock; releasing it raised
    ``OperationalError ... SELECT pg_advisory_unlock`` and killed the worker, its trial left
    RUNNING. The lock is gone with its connection: release logs it, the next lock is taken."""
    with caplog.at_level("WARNING", logger="ermrl.storage"):
        with storage_lock(postgres_url, "s"):
            (holder,) = _advisory_holders(pg_admin, postgres_url)
            with pg_admin.cursor() as cur:  # type: ignore[attr-defined]
                cur.execute("SELECT pg_terminate_backend(%s)", (holder,))
    assert "was lost with its connection" in caplog.text
    with storage_lock(postgres_url, "s", retry_window=10):
        assert len(_advisory_holders(pg_admin, postgres_url)) == 1


def test_a_lock_reuses_its_connection(postgres_url: str, pg_admin: object) -> None:
    """Every lock opened a connection of its own: a busy study used up the server's."""
    holders = []
    for _ in range(3):
        with storage_lock(postgres_url, "s"):
            holders += _advisory_holders(pg_admin, postgres_url)
    assert len(holders) == 3 and len(set(holders)) == 1


@pytest.mark.timeout(60)
def test_taking_a_lock_waits_while_the_server_has_no_connection_left(
    postgres_url: str, pg_admin: object, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Out of connections (here: the role's limit, 0 for 1.5 s), a lock's connect failed with a
    traceback at once; it is now retried with the storage's backoff."""
    role = f"ermrl_lock_{uuid.uuid4().hex[:8]}"
    with pg_admin.cursor() as cur:  # type: ignore[attr-defined]
        cur.execute(f"CREATE ROLE {role} LOGIN CONNECTION LIMIT 0")
    parts = urlsplit(postgres_url)
    url = urlunsplit(parts._replace(netloc=f"{role}@{parts.hostname}:{parts.port or 5432}"))

    def allow() -> None:
        time.sleep(1.5)
        with pg_admin.cursor() as cur:  # type: ignore[attr-defined]
            cur.execute(f"ALTER ROLE {role} CONNECTION LIMIT -1")

    thread = threading.Thread(target=allow)
    try:
        thread.start()
        start = time.monotonic()
        monkeypatch.setenv("ERMRL_STORAGE_RETRY_S", "30")
        with storage_lock(url, "s"):
            assert time.monotonic() - start > 1
    finally:
        thread.join()
        for key in [k for k in locks_module._ENGINES if role in k]:
            locks_module._ENGINES.pop(key).dispose()
        with pg_admin.cursor() as cur:  # type: ignore[attr-defined]
            cur.execute(f"DROP ROLE {role}")
