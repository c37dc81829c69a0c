"""Storage URLs, parsed once into a small frozen value.

Every other module of [`ermrl.storage`][ermrl.storage] takes a
[`StorageURL`][ermrl.storage.StorageURL] from [`parse_storage_url`][ermrl.storage.parse_storage_url]
instead of taking the string apart again. This module is a leaf: it imports nothing else from
[`ermrl.storage`][ermrl.storage], so any of them can import it.

Accepted URLs:

- ``sqlite:///path.db`` (in-memory databases are refused, however spelled: ``sqlite://``,
  ``sqlite:///:memory:``, ``sqlite:///file::memory:?uri=true``, ``...?mode=memory``, with
  percent-escapes; no later command could read their trials). A file is named by its plain
  path: percent-escapes and SQLite URI filenames (``file:...``) are refused, since SQLite would
  decode them into another file than the one ermrl checks;
- ``postgresql://...`` (or ``postgres://...``) and ``mysql://...``, with or without a driver
  (``postgresql+psycopg2://``, ``mysql+pymysql://``);
- ``journal:///path.log`` or any path ending in ``.log`` (no scheme);
- ``redis://host:port[/db][?prefix=NAME]``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal
from urllib.parse import parse_qsl, unquote, urlencode, urlsplit, urlunsplit

__all__ = [
    "CONNECT_TIMEOUT_S",
    "StorageError",
    "StorageKind",
    "StorageURL",
    "bound_handshake",
    "connect_args",
    "dashboard_command",
    "journal_file",
    "parse_storage_url",
    "redis_split",
    "sqlite_file",
]

StorageKind = Literal["sqlite", "journal", "postgresql", "mysql", "redis"]
_RDB_KINDS = ("sqlite", "postgresql", "mysql")
# Seconds a database server has to accept a connection and finish its handshake (PostgreSQL's
# connect_timeout; for MySQL the greeting and login too, which PyMySQL reads without a limit).
CONNECT_TIMEOUT_S = 10.0


class StorageError(RuntimeError):
    """The storage URL is malformed or the storage cannot be reached."""


@dataclass(frozen=True)
class StorageURL:
    """A storage URL, taken apart once (build it with
    [`parse_storage_url`][ermrl.storage.parse_storage_url]).

    Attributes:
        raw: The URL as given (what error messages and
            [`ermrl.storage.storage_url`][ermrl.storage.storage_url] show).
        kind: ``"sqlite"``, ``"journal"``, ``"postgresql"``, ``"mysql"`` or ``"redis"``.
        url: What the backend is opened with: the SQLAlchemy URL for ``sqlite``,
            ``postgresql`` and ``mysql`` (``postgres://`` spelled ``postgresql``, a driver
            filled in when none is given), the Redis URL without the ``prefix`` parameter for
            ``redis``, and ``raw`` for ``journal``.
        path: The database file (``sqlite``) or log file (``journal``), ``~`` expanded;
            ``None`` for server storages.
        prefix: The key prefix of a Redis journal (``?prefix=NAME``); ``""`` when none is given
            and for every other kind.
    """

    raw: str
    kind: StorageKind
    url: str
    path: Path | None = None
    prefix: str = ""

    @property
    def is_rdb(self) -> bool:
        """Whether Optuna opens it as an ``RDBStorage`` (SQLite, PostgreSQL, MySQL)."""
        return self.kind in _RDB_KINDS

    def __str__(self) -> str:
        return self.raw


def parse_storage_url(url: str) -> StorageURL:
    """Take a storage URL apart (see the module docstring for the accepted forms).

    Args:
        url: The storage URL, e.g. ``sqlite:///ermrl.db`` or ``redis://localhost:6379?prefix=a``.

    Returns:
        The parsed URL; ``parse_storage_url("postgres://u@h/db").url`` is
        ``"postgresql+psycopg2://u@h/db"`` when psycopg 3 is not installed.

    Raises:
        StorageError: an unsupported URL, or an in-memory SQLite database (one line each).
    """
    if url.startswith("journal://") or (url.endswith(".log") and "://" not in url):
        return StorageURL(raw=url, kind="journal", url=url, path=journal_file(url))
    scheme, _, rest = url.partition("://") if "://" in url else ("", "", url)
    dialect, _, driver = scheme.lower().partition("+")
    if dialect == "sqlite":
        path = sqlite_file(url)
        # Percent-escapes are decoded by SQLAlchemy and again by SQLite (in a URI filename):
        # an in-memory database may hide behind one or two layers of them.
        if path is None or any(_sqlite_in_memory(u) for u in _unquoted(url)):
            raise StorageError(
                f"{url} is an in-memory SQLite database: its trials would vanish when this "
                "command exits and no other command could read them; use a file, e.g. "
                "sqlite:///ermrl.db"
            )
        problem = _sqlite_spelling_problem(url)
        if problem is not None:
            raise StorageError(
                f"{url}: {problem}, so SQLite could write another file than the one named; "
                "write the database file's path as it is, e.g. sqlite:///ermrl.db"
            )
        return StorageURL(raw=url, kind="sqlite", url=url, path=path)
    if dialect in ("postgresql", "postgres"):
        # SQLAlchemy 2.1 defaults to psycopg 3; without it, use psycopg2.
        driver = driver or ("" if _installed("psycopg") else "psycopg2")
        return StorageURL(raw=url, kind="postgresql", url=_with_scheme("postgresql", driver, rest))
    if dialect == "mysql":
        driver = driver or ("" if _installed("MySQLdb") else "pymysql")
        return StorageURL(raw=url, kind="mysql", url=_with_scheme("mysql", driver, rest))
    if dialect == "redis":
        clean, prefix = redis_split(url)
        return StorageURL(raw=url, kind="redis", url=clean, prefix=prefix)
    raise StorageError(
        f"unsupported storage URL {url!r}; use sqlite:///file.db, postgresql://..., "
        "mysql://..., journal:///file.log (or file.log) or redis://host:port"
    )


def dashboard_command(url: str) -> str | None:
    """The ``optuna-dashboard`` command that shows the studies of ``url`` live.

    optuna-dashboard (the ``viz`` extra) takes SQLAlchemy URLs, a journal file's path and a
    Redis URL; it reads a Redis journal without a key prefix only, so a ``?prefix=`` URL gets
    ``None``, as does a URL that does not parse.
    """
    import shlex

    try:
        parsed = parse_storage_url(url)
    except StorageError:
        return None
    if parsed.kind == "redis" and parsed.prefix:
        return None
    target = str(parsed.path) if parsed.kind == "journal" else parsed.url
    return f"optuna-dashboard {shlex.quote(target)}"


def sqlite_file(url: str) -> Path | None:
    """The database file of a ``sqlite:///`` URL (``None`` for in-memory databases)."""
    if _sqlite_in_memory(url):
        return None
    rest = url.split("://", 1)[1] if "://" in url else url
    rest = rest[1:] if rest.startswith("/") else rest  # sqlite:///rel.db, sqlite:////abs.db
    rest = rest.split("?", 1)[0]
    if not rest:
        return None
    return Path(rest).expanduser()


def _unquoted(url: str) -> list[str]:
    """``url`` percent-decoded once and twice (the decodings SQLAlchemy and SQLite apply)."""
    once = unquote(url)
    return [once, unquote(once)]


def _sqlite_spelling_problem(url: str) -> str | None:
    """Why a SQLite URL of a file is refused: percent-escapes or a SQLite URI filename
    (``file:...``), whose file SQLite names otherwise than the path ermrl reads from the URL
    (for its locks, existence and read-only checks); ``None`` for a plain path."""
    rest = url.split("://", 1)[1] if "://" in url else url
    if "%" in rest:
        return "percent-escapes (%XX) are decoded differently by SQLAlchemy and SQLite"
    database = rest[1:] if rest.startswith("/") else rest
    if database.lower().startswith("file:"):
        return "a SQLite URI filename (file:...) names its file otherwise than a path"
    return None


def _sqlite_in_memory(url: str) -> bool:
    """Whether a SQLite URL names an in-memory database, however it is spelled.

    The URL is read as SQLAlchemy reads it (percent-decoded, query taken apart), then matched
    without regard to case: no path, ``:memory:``, a SQLite URI filename ``file::memory:`` or
    ``file:`` alone, or a query with ``mode=memory`` or ``vfs=memdb`` in any position.
    """
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError

    try:
        parsed = make_url(url)
    except (ArgumentError, ValueError):
        return False  # not a URL SQLAlchemy could open: left to the path checks
    database = (parsed.database or "").lower()
    if database.startswith("file:"):
        database = database[len("file:") :].split("?", 1)[0] or ":memory:"
    if database in ("", ":memory:"):
        return True
    for key, values in parsed.query.items():
        for value in (values,) if isinstance(values, str) else values:
            if (key.lower(), value.lower()) in (("mode", "memory"), ("vfs", "memdb")):
                return True
    return False


def journal_file(url: str) -> Path:
    """The log file of a ``journal:///path`` URL or of a bare ``path.log``."""
    if url.startswith("journal://"):
        return Path(url[len("journal://") :]).expanduser()
    return Path(url).expanduser()


def redis_split(url: str) -> tuple[str, str]:
    """Split ``redis://host:port/db?prefix=NAME`` into the Redis URL and the key prefix."""
    parts = urlsplit(url)
    query = parse_qsl(parts.query, keep_blank_values=True)
    prefix = "".join(v for k, v in query if k == "prefix")
    rest = urlencode([(k, v) for k, v in query if k != "prefix"])
    return urlunsplit(parts._replace(query=rest)), prefix


def _with_scheme(dialect: str, driver: str, rest: str) -> str:
    return f"{dialect}+{driver}://{rest}" if driver else f"{dialect}://{rest}"


@functools.cache
def _installed(module: str) -> bool:
    """Whether a database driver can be imported (checked once per process)."""
    try:
        __import__(module)
    except ImportError:
        return False
    return True


def connect_args(spec: StorageURL) -> dict[str, Any]:
    """Driver arguments that bound how long connecting to a server storage may take.

    PostgreSQL (libpq) and mysqlclient apply ``connect_timeout`` (`CONNECT_TIMEOUT_S`) to
    the whole connection, handshake included. PyMySQL applies it to the TCP connection only and
    then waits for the server's greeting without a limit: against a server that never sends one
    (another service's port, a silent listener) ``mysql://`` hung for a minute or forever. Its
    read and write timeouts bound the handshake to the same time; `bound_handshake` lifts
    them once a connection is made, so a long query or lock wait is not cut short.

    Args:
        spec: A parsed ``postgresql`` or ``mysql`` storage URL.

    Returns:
        The ``connect_args`` of ``sqlalchemy.create_engine`` (empty for other kinds).
    """
    if spec.kind not in ("postgresql", "mysql"):
        return {}
    timeout = CONNECT_TIMEOUT_S
    args: dict[str, Any] = {"connect_timeout": max(1, round(timeout))}
    if spec.kind == "mysql" and "+pymysql" in spec.url.split("://", 1)[0]:
        args.update(read_timeout=timeout, write_timeout=timeout)
    return args


def bound_handshake(engine: Any) -> Any:
    """Lift PyMySQL's handshake-time read and write timeouts (`connect_args`) from the
    connections of ``engine`` when they are checked out, so only connecting is bounded.

    PyMySQL has no public setter: it keeps the timeouts in ``_read_timeout`` and
    ``_write_timeout`` and applies them to its socket before each read and write.

    Args:
        engine: A SQLAlchemy engine (other drivers' connections are left alone).

    Returns:
        ``engine``.
    """
    import sqlalchemy

    def lift(dbapi_connection: Any, *_: Any) -> None:
        if type(dbapi_connection).__module__.startswith("pymysql"):
            dbapi_connection._read_timeout = None
            dbapi_connection._write_timeout = None

    sqlalchemy.event.listen(engine, "checkout", lift)
    return engine
