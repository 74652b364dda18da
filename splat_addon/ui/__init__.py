"""The interface: the Splats panel and the add-on preferences."""
