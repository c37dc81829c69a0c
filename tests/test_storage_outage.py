"""Storage servers that do not answer: connecting is bounded in time and fails in one line, and a
worker rides out a short outage by retrying its storage calls."""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator

import pytest
import sqlalchemy

import ermrl.storage._url as url_module
from ermrl.storage import StorageError, open_storage


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
@pytest.mark.parametrize("scheme", ["mysql", "mysql+pymysql", "postgresql"])
def test_a_server_that_never_greets_fails_in_one_line(
    silent_port: int, scheme: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """PyMySQL waited for the greeting without a limit (over 100 s against a silent listener,
    61 s against PostgreSQL's port); now the connect timeout covers it (10 s, 1 s here)."""
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
