"""Sample assets of vbusd and the generators that make them (not installed with the package)."""
