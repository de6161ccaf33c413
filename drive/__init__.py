"""The drive layer: a drive's data model, its writer and its reader (docs/architecture.md), below acquire and replay."""
