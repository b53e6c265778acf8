"""The project's tests, laid out like the code they test.

Every test folder is a package, so modules of the same name in different folders import as different
modules (``tests.services.emulator.test_sessions``, ``tests.services.emulator.routes.test_sessions``)
and shared code imports by its full name (``tests.helpers``, ``tests.services.controller.ctl``).
"""
