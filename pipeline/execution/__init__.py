"""How the pipeline runs: `run` launches one stage on pinned numeric code paths, `preload` keeps a warm
interpreter that forks each stage, `repro` runs dvc.yaml's stages on both cores, `workers` spreads a
stage's independent jobs over them (docs/reproducibility.md), `dvc_api` runs DVC in this process for
`needlecue retrain`."""
