"""Packaged schemas: the USD plugin (usd/) and the JSON Schemas of layout metadata and reports."""
