"""Validators of Virtual Bones assets: findings with stable codes, severities and locations.

Entry point: :func:`vbusd.validators.api.validate` (behind ``vbusd validate``) returns a
:class:`~vbusd.validators.report.Report`; it raises only when the asset cannot be opened at all.

Modules: ``codes`` (the one registry of codes; ``python -m vbusd.format.codes --markdown``
generates spec/ISSUES.md), ``findings`` (Finding and its four location kinds), ``declared`` (what a
prim or a metadata document declares), ``rawtexture`` (never-raising texture and metadata access),
``checks_animation``, ``checks_texels``, ``checks_bindings`` (the checks), ``report`` (text and JSON
reports), ``usd_validation`` (registration with OpenUSD's UsdValidation). Importing this package
imports nothing heavy; pxr, OpenEXR and jsonschema load when a check needs them.
"""
