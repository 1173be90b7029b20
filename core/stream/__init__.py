"""The progressive stream: format, writer, readers, HTTP client. Blender tier: numpy and stdlib only."""
