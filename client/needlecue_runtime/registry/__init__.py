"""The registry as the client sees it: where MLflow lives and the files of a registered version
(store), MLflow's environment (mlflow_env) and the signed manifests of a published bucket (manifest).
The pipeline's registering side is `pipeline.registry`."""
