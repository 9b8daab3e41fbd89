"""The demo scene bundled with anisdf (``bunny_plastic/``, see its SOURCES.md): what ``anisdf demo`` trains."""
