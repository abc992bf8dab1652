"""``safenav render``: fly one episode and write a GIF."""
