"""Converters from source formats (UsdSkel, glTF 2.0) to the vbusd data model; see registry.py."""
