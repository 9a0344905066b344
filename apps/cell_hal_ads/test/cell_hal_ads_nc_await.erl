%% Waits the suites of the NC's objects over ADS share: a job's end as its owner hears
%% it, and an object's status.
-module(cell_hal_ads_nc_await).
-include_lib("stdlib/include/assert.hrl").

-export([done/1, await/2, status/2]).

-define(WAIT, 15000).

%% A command accepted and its job done.
done({ok, Ref}) ->
    await(Ref, done);
done(Other) ->
    ct:fail({refused, Other}).

%% The job's end, which must be `What'.
await(Ref, What) ->
    receive {Ref, Got} -> ?assertEqual(What, Got), ok
    after ?WAIT -> ct:fail({no_end, What})
    end.

%% The object's status: the present one, or the change to it.
status(Id, Want) ->
    flush(Id),
    case cell_hal_hw:subscribe(Id) of
        {ok, Want} ->
            ok;
        {ok, _} ->
            receive {cell_hal_hw, Id, Want} -> ok
            after ?WAIT -> ct:fail({status_not, Id, Want})
            end
    end.

flush(Id) ->
    receive {cell_hal_hw, Id, _} -> flush(Id)
    after 0 -> ok
    end.
