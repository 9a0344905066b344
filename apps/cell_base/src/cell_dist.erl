%% @doc The node's door to the Erlang distribution: whether its cookie and the address
%% it listens on are fit for the machine. Whoever can connect to the node with its
%% cookie can run any code on it, so `bin/cellrt' sets both before the VM starts: the
%% cookie from `$CELLRT_COOKIE' or the cell root's `Distribution/cookie' (made at the
%% first start, readable by its owner only), the address from `$CELLRT_DIST_BIND'
%% (127.0.0.1 unless set). At boot the node checks what it was given: a production
%% build refuses a cookie anyone could guess, and a cell whose peers are on other PCs
%% is told when its node listens on this PC only.
-module(cell_dist).

-export([check_cookie/2, unreachable_peers/3, listen_interface/0]).

%% The cookie the release used to ship with, printed in old instructions.
-define(GUESSABLE, [cellrt, '']).

%% @doc Whether a node may run with `Cookie': `ok', a warning to log, or (in a
%% production build, `Prod') the refusal to start.
-spec check_cookie(atom(), boolean()) -> ok | {warning, binary()} | {error, binary()}.
check_cookie(Cookie, Prod) ->
    case lists:member(Cookie, ?GUESSABLE) of
        false ->
            ok;
        true ->
            Text = iolist_to_binary(
                     ["the node's distribution cookie is ", describe(Cookie), ", which anyone "
                      "can guess and then run any code on the node. Unset CELLRT_COOKIE: "
                      "bin/cellrt then makes a random one in the cell root's "
                      "Distribution/cookie at the first start (or set CELLRT_COOKIE to a "
                      "long random word)."]),
            case Prod of
                true -> {error, <<"a production build does not start: ", Text/binary>>};
                false -> {warning, Text}
            end
    end.

describe('') -> "empty";
describe(Cookie) -> ["the well-known `", atom_to_list(Cookie), "'"].

%% @doc The peers among `Peers' this node cannot reach while its distribution listens
%% on `Interface' (`undefined': every network of the PC): those on another PC when it
%% listens on a loopback address. A peer on this PC is one of the same host as `Self',
%% or of `localhost'.
-spec unreachable_peers(inet:ip_address() | undefined, node(), [node()]) -> [node()].
unreachable_peers(Interface, Self, Peers) ->
    case is_loopback(Interface) of
        false ->
            [];
        true ->
            Here = host(Self),
            [P || P <- Peers, not lists:member(host(P), [Here, "localhost"])]
    end.

%% @doc The address the distribution of this node listens on, as the release sets it
%% (`undefined': every network of the PC).
-spec listen_interface() -> inet:ip_address() | undefined.
listen_interface() ->
    case application:get_env(kernel, inet_dist_use_interface) of
        {ok, Ip} when is_tuple(Ip) -> Ip;
        _ -> undefined
    end.

is_loopback({127, _, _, _}) -> true;
is_loopback({0, 0, 0, 0, 0, 0, 0, 1}) -> true;
is_loopback(_) -> false.

host(Node) ->
    case string:split(atom_to_list(Node), "@") of
        [_, Host] -> Host;
        [_] -> ""
    end.

-ifdef(TEST).
-include_lib("eunit/include/eunit.hrl").

check_cookie_test_() ->
    [?_assertEqual(ok, check_cookie('c07635a4d92e15e77c819f3f4f8b118a', true)),
     ?_assertEqual(ok, check_cookie(cellrt_ct, true)),
     ?_assertMatch({error, <<"a production build does not start: ", _/binary>>},
                   check_cookie(cellrt, true)),
     ?_assertMatch({error, _}, check_cookie('', true)),
     ?_assertMatch({warning, _}, check_cookie(cellrt, false)),
     ?_assertMatch({warning, _}, check_cookie('', false)),
     ?_assertEqual(ok, check_cookie(other, false))].

check_cookie_says_what_to_do_test() ->
    {error, Text} = check_cookie(cellrt, true),
    [?assertNotEqual(nomatch, binary:match(Text, Part), Part)
     || Part <- [<<"`cellrt'">>, <<"CELLRT_COOKIE">>, <<"Distribution/cookie">>]],
    {error, Empty} = check_cookie('', true),
    ?assertNotEqual(nomatch, binary:match(Empty, <<"is empty">>)).

unreachable_peers_test_() ->
    Self = 'cell1@pc1',
    Peers = ['cell2@pc1', 'cell3@localhost', 'cell4@pc2', 'cell5@10.0.0.7'],
    [?_assertEqual(['cell4@pc2', 'cell5@10.0.0.7'],
                   unreachable_peers({127, 0, 0, 1}, Self, Peers)),
     ?_assertEqual(['cell4@pc2', 'cell5@10.0.0.7'],
                   unreachable_peers({127, 0, 1, 1}, Self, Peers)),
     ?_assertEqual(['cell4@pc2', 'cell5@10.0.0.7'],
                   unreachable_peers({0, 0, 0, 0, 0, 0, 0, 1}, Self, Peers)),
     ?_assertEqual([], unreachable_peers({0, 0, 0, 0}, Self, Peers)),
     ?_assertEqual([], unreachable_peers({192, 168, 1, 10}, Self, Peers)),
     ?_assertEqual([], unreachable_peers(undefined, Self, Peers)),
     ?_assertEqual([], unreachable_peers({127, 0, 0, 1}, Self, ['cell2@pc1'])),
     ?_assertEqual([], unreachable_peers({127, 0, 0, 1}, Self, []))].
-endif.
