"""PostgreSQL: MLflow's tracking, registry and auth stores. PostgreSQL refuses to run as root, so
under root its data folder is `/var/lib/postgresql/needlecue-team/<id>`, owned by `postgres`; it is
started and stopped through `pg_ctl`, and found again by its `postmaster.pid`."""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
from pathlib import Path

from pipeline.team.servers.base import Launch, Server, StackError, run

USER = "needlecue"  # the database role MLflow connects as
DATABASES = ("mlflow", "mlflow_auth")  # tracking + registry, and basic auth's users and permissions


class Postgres(Server):
    name = "postgres"

    @property
    def data_dir(self) -> Path:
        """Its data folder: in the state folder, or under root in postgres's own home."""
        if os.geteuid() != 0:
            return self.stack.dir / "postgres"
        key = hashlib.sha256(str(self.stack.dir).encode()).hexdigest()[:12]
        return Path("/var/lib/postgresql/needlecue-team") / key / "data"

    @property
    def log(self) -> Path:
        return self.data_dir.parent / "postgres.log"

    def uri(self, database: str) -> str:
        """SQLAlchemy URI of one of its databases (psycopg2: `postgresql://` picks psycopg 3)."""
        password = self.stack.settings["postgres_password"]
        return f"postgresql+psycopg2://{USER}:{password}@{self.stack.host}:{self.port}/{database}"

    def _options(self) -> list[str]:
        return ["-p", str(self.port), "-h", self.stack.host, "-k", str(self.data_dir)]

    def _as_postgres(self, cmd: list[str]) -> list[str]:
        return ["runuser", "-u", "postgres", "--", *cmd] if os.geteuid() == 0 else cmd

    def launch(self) -> Launch:
        """Its foreground command. The data folder must exist: `team start` makes it (initdb) the
        first time."""
        cmd = [str(postgres_bin() / "postgres"), "-D", str(self.data_dir), *self._options()]
        return Launch(cmd, {}, self.data_dir, "postgres" if os.geteuid() == 0 else None)

    def start(self) -> None:
        """initdb the first time, then `pg_ctl start` (waiting), then the databases MLflow uses."""
        bin_dir, data = postgres_bin(), self.data_dir
        if not (data / "PG_VERSION").is_file():
            self._initdb(bin_dir, data)
        run(
            self._as_postgres(
                [
                    str(bin_dir / "pg_ctl"), "-D", str(data), "-l", str(self.log),
                    "-o", " ".join(self._options()), "-w", "-t", "60", "start",
                ]
            ),
            f"postgres: start (log {self.log})",
        )  # fmt: skip
        self._create_databases()

    def _initdb(self, bin_dir: Path, data: Path) -> None:
        data.parent.mkdir(parents=True, exist_ok=True)
        pwfile = data.parent / "pwfile"
        pwfile.write_text(self.stack.settings["postgres_password"] + "\n")
        if os.geteuid() == 0:
            shutil.chown(data.parent, "postgres", "postgres")
            shutil.chown(pwfile, "postgres", "postgres")
        os.chmod(data.parent, 0o700)
        os.chmod(pwfile, 0o600)
        try:
            run(
                self._as_postgres(
                    [
                        str(bin_dir / "initdb"), "-D", str(data), "-U", USER, "--auth=scram-sha-256",
                        f"--pwfile={pwfile}", "--encoding=UTF8", "--locale=C",
                    ]
                ),
                "postgres: initdb",
            )  # fmt: skip
        finally:
            pwfile.unlink(missing_ok=True)

    def _create_databases(self) -> None:
        import psycopg2

        con = psycopg2.connect(
            host=self.stack.host,
            port=self.port,
            user=USER,
            password=self.stack.settings["postgres_password"],
            dbname="postgres",
            connect_timeout=10,
        )
        con.autocommit = True
        with contextlib.closing(con), con.cursor() as cur:
            for db in DATABASES:
                cur.execute("SELECT 1 FROM pg_database WHERE datname = %s", (db,))
                if cur.fetchone() is None:
                    cur.execute(f'CREATE DATABASE "{db}"')

    def recorded_pid(self) -> int | None:
        try:
            return int((self.data_dir / "postmaster.pid").read_text().split()[0])
        except (OSError, ValueError, IndexError):
            return None

    def stop(self, kill: bool = False) -> bool:
        """`pg_ctl stop -m fast`, or SIGKILL to the postmaster with `kill`."""
        if kill or self.pid() is None:
            return super().stop(kill)
        stop = [str(postgres_bin() / "pg_ctl"), "-D", str(self.data_dir), "-m", "fast", "-w", "stop"]
        run(self._as_postgres(stop), "postgres: stop")
        return True

    def _signal(self, pid: int, sig: int) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, sig)  # the postmaster alone: it is not a session leader of ours


def postgres_bin() -> Path:
    """The folder of PostgreSQL's server programs (Debian: /usr/lib/postgresql/<version>/bin)."""
    found = sorted(Path("/usr/lib/postgresql").glob("*/bin/pg_ctl"), key=lambda p: int(p.parent.parent.name))
    if found:
        return found[-1].parent
    on_path = shutil.which("pg_ctl")
    if on_path:
        return Path(on_path).resolve().parent
    raise StackError("PostgreSQL's server is not installed: `apt-get install postgresql` (make setup-team)")
