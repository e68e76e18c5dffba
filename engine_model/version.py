"""The package version, recorded in every plan, manifest and run folder."""

__version__ = "0.2.0"


def package_version() -> str:
    """Installed distribution version of ``engine-model`` (the source tree's :data:`__version__` if not installed)."""
    import importlib.metadata

    try:
        return importlib.metadata.version("engine-model")
    except importlib.metadata.PackageNotFoundError:  # running from a source tree
        return __version__
