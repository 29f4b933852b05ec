"""Scene data: the one scene-folder writer and reader, detection tables, AI2-THOR names and the lineage's file
formats (docs/ARCHITECTURE.md)."""
