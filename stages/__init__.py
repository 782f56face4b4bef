"""The pipeline stages, in the order they run (declared here once), and the runner that caches them.

Each stage module follows the protocol in `fullview.stages.protocol`: `VERSION`, `UPSTREAM`, `INPUTS` and
`run(ctx) -> summary`. A new stage is a module here plus its name in `PIPELINE` and its options class in
`fullview.sfm.options.OPTIONS_BY_SECTION`.
"""

PIPELINE: tuple[str, ...] = ("features", "matches", "filter", "epipoles", "registration", "triangulation", "densify")
