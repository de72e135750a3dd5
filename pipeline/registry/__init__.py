"""The model registry: where MLflow lives (store), tracking each trained model as a run
(tracking), the champion rule as a pure function (champion), and registering and rolling back
versions (versions)."""
