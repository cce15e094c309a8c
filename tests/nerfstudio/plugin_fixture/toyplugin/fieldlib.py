from toyplugin.model import ToyField


class PlainField(ToyField):
    """The toy field, defined in a module the hidden-field model only reaches as a module object."""
