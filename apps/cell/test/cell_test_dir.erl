%% @doc Fresh folders for tests, inside the build tree (beside the compiled tests), so
%% a test run leaves nothing behind outside `_build/'.
-module(cell_test_dir).

-export([new/2]).

%% A new empty folder `<build>/test-files/<Suite>/<What>-<unique>'.
new(Suite, What) ->
    Base = filename:dirname(filename:dirname(code:which(?MODULE))),
    Dir = filename:join([Base, "test-files", Suite,
                         What ++ "-" ++ os:getpid() ++ "-"
                         ++ integer_to_list(erlang:unique_integer([positive]))]),
    ok = filelib:ensure_dir(filename:join(Dir, "x")),
    Dir.
