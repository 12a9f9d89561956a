"""The viser UI of handanno (the only package that imports viser): the server, one ClientUI per
browser, the shared hand scene and the Annotate / Review panels. It calls ``app.control``."""
