"""Specialists trained elsewhere in, the front's policies out (docs/import_export.md)."""
