"""Importers that turn public recording formats into Locus sites through the HTTP API."""
