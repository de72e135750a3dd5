"""A bucket kept in a folder: what the lab's publisher writes (put_object, head_object), as a local
copy of the published bucket (`aws s3 sync`) would hold it."""

from __future__ import annotations

from pathlib import Path
from typing import Any


class FolderBucket:
    """The two S3 calls publishing makes, on files under `root` (keys are relative paths)."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)

    def put_object(self, *, Bucket: str, Key: str, Body: bytes, **_: Any) -> None:
        path = self.root / Key
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(Body)

    def head_object(self, *, Bucket: str, Key: str) -> dict:
        from botocore.exceptions import ClientError

        if not (self.root / Key).is_file():
            raise ClientError(
                {"ResponseMetadata": {"HTTPStatusCode": 404}, "Error": {"Code": "404"}}, "HeadObject"
            )
        return {}
