"""The HTTP routes, a module each: thin, they call the documents and ``answers``."""

__all__: list[str] = []  # a package of modules: each declares its own
