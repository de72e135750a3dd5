"""The team stack on one machine: PostgreSQL, SeaweedFS (S3) and an MLflow server with basic auth."""
