"""What people do with the plugin: render a scene file, make movies, explore in the browser;
and where a checkout keeps its scenes."""
