"""Validators of Virtual Bones assets: findings with stable codes, severities and locations."""
