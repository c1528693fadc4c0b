"""The format itself, as pure data and math: layout, model, encodings, metadata, codes, errors.

Nothing here reads or writes files; the modules need only numpy (jsonschema for metadata checks).
"""
