"""I/O at the edges: one reader and one writer per container (EXR, PNG, sidecar JSON, USD) and
the file layer every write goes through (atomic commits, safe paths)."""
