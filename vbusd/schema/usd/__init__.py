"""The codeless USD schema plugin files (schema.usda, generatedSchema.usda, plugInfo.json)."""
