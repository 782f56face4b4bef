"""Commands other than the pipeline stages: `eval`, `compare`, `colmap-check`, `export`.

Each module has one entry function taking the Pipeline (dataset, workspace, config) and its options; it reads
artifacts through the workspace and writes its own outputs in a transaction, like a stage. A new command is a
module here plus a subparser in `fullview.cli`.
"""
