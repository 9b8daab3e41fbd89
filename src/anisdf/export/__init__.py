"""Mesh extraction and export, pictures and videos."""
