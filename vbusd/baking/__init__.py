"""Baking: a sampled skinned animation into a Virtual Bones texture (the baker, levels of detail, root motion)."""
