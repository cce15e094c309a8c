"""A third-party-style nerfstudio plugin written for the tests: its own Field and Model, classes
sp-plugins has never seen. Not a test module; tests install it as a temporary distribution."""
