"""Import OpenScene log pickles and nuPlan map GeoPackages into `navsim-lb/scene` files.

Modules: `log_pickle` (restricted loader), `frames` (devkit frame conversion, scene windows),
`gpkg` (GeoPackage reader), `excerpt` (per-scene map excerpt), `navigation` (driving command),
`importer` (parallel, resumable import), `curation` (split curation), `cli` (subcommands).
"""
