import inspect

import geocd.errors as E


def test_every_error_is_a_geocd_error_and_a_builtin():
    classes = [c for _, c in inspect.getmembers(E, inspect.isclass) if issubclass(c, Exception)]
    assert len(classes) > 10
    for c in classes:
        assert issubclass(c, E.GeoCDError), c
        if c is not E.GeoCDError and c is not E.CancelledError:
            builtin_bases = [
                b for b in c.__mro__ if b.__module__ == "builtins" and b not in (Exception, BaseException, object)
            ]
            assert builtin_bases, f"{c.__name__} inherits no fitting builtin"


def test_examples():
    assert issubclass(E.RPCParseError, ValueError)
    assert issubclass(E.InputFileNotFoundError, FileNotFoundError)
    assert issubclass(E.OutputError, OSError)
