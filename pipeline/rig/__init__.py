"""The rig-log/1 raw format and its ingestion: the contract, reading and validating batch folders,
and the per-batch Parquet cache the ingest stage keeps (see `docs/rig-log-format.md`)."""
