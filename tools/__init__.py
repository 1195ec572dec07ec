"""Developer tools (wheel fetching, extension build); not shipped in the extension zip."""
