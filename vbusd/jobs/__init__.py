"""Jobs: the work a command does, from start to committed files (convert, batch, crowd, export, decode)."""
