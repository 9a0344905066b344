%% @doc Traceability (seed 004): every inspection that received an image (point, part
%% serial, result, string, time, image reference, the camera) and every override
%% (employee, point, serial, time, the inspection it overrides), in the cell's
%% database ({@link cell_db}), queryable by part serial.
%%
%% Writes are flushed to the disk before they return ({@link cell_db:sync_transaction/1}):
%% the block reports Complete to the PLC only once the record is safe. Each is also
%% added to the part's history in the cell's traceability ({@link cell_stats:record/3}),
%% beside what the cell's tasks did with it.
-module(cell_inspect_db).

-export([tables/0, start/0, record_inspection/1, log_override/1, by_serial/1]).

-export_type([inspection/0, override/0]).

-record(cell_inspect_inspection,
        {id :: {integer(), integer()},          %% {time in µs, a unique integer}
         block :: atom(),
         point :: binary(),
         serial :: binary(),
         result :: pass | fail | error,
         code :: cell_inspect_status:error_name(),
         text :: binary(),
         client :: binary(),
         image :: binary(),                     %% a file under Data/, or the camera's own
         time :: integer()}).                   %% UTC, ms
-record(cell_inspect_override,
        {id :: {integer(), integer()},
         block :: atom(),
         point :: binary(),
         serial :: binary(),
         employee :: binary(),
         inspection :: {integer(), integer()},
         time :: integer()}).

-type inspection() :: #{block := atom(), point := binary(), serial := binary(),
                        result := pass | fail | error,
                        code => cell_inspect_status:error_name(),
                        text => binary(), client => binary(), image => binary(),
                        time => integer()}.
-type override() :: #{block := atom(), point := binary(), serial := binary(),
                      employee := binary(), time => integer()}.

-define(INSPECTIONS, cell_inspect_inspection).
-define(OVERRIDES, cell_inspect_override).
-define(WAIT_MS, 30000).

%% @doc This app's tables, for {@link cell_db:ensure_tables/2}.
-spec tables() -> [cell_db:table()].
tables() ->
    [{?INSPECTIONS, [{attributes, record_info(fields, cell_inspect_inspection)},
                     {index, [#cell_inspect_inspection.serial]}, {type, set}]},
     {?OVERRIDES, [{attributes, record_info(fields, cell_inspect_override)},
                   {index, [#cell_inspect_override.serial]}, {type, set}]}].

%% @doc Starts the database and makes sure this app's tables are there.
-spec start() -> ok | {error, cell_db:error()}.
start() ->
    case cell_db:start() of
        ok -> cell_db:ensure_tables(tables(), ?WAIT_MS);
        E -> E
    end.

%% @doc Records an inspection; returns its id.
-spec record_inspection(inspection()) -> {ok, term()} | {error, term()}.
record_inspection(#{block := B, point := P, serial := S, result := R} = I) ->
    Time = maps:get(time, I, os:system_time(millisecond)),
    Rec = #cell_inspect_inspection{id = new_id(), block = B, point = P, serial = S,
                                   result = R, code = maps:get(code, I, no_error),
                                   text = maps:get(text, I, <<>>),
                                   client = maps:get(client, I, <<>>),
                                   image = maps:get(image, I, <<>>), time = Time},
    case cell_db:sync_transaction(fun() -> mnesia:write(Rec) end) of
        {atomic, ok} ->
            Detail = maps:with([point, result, code, text, image], inspection_map(Rec)),
            ok = history(S, inspection, Detail#{block => B}),
            {ok, Rec#cell_inspect_inspection.id};
        {aborted, Why} ->
            {error, Why}
    end.

%% @doc Override step 4: finds the latest result (PASS or FAIL) of this block for the
%% point and the part serial and logs the override against it, in one transaction.
%% An override needs a part serial: without one nothing is found.
-spec log_override(override()) -> {ok, term()} | not_found | {error, term()}.
log_override(#{serial := <<>>}) ->
    not_found;
log_override(#{block := B, point := P, serial := S, employee := E} = O) ->
    Time = maps:get(time, O, os:system_time(millisecond)),
    Fun = fun() ->
                  Results = [I || #cell_inspect_inspection{block = Bx, point = Px, result = R} = I
                                      <- mnesia:index_read(?INSPECTIONS, S,
                                                           #cell_inspect_inspection.serial),
                                  Bx =:= B, Px =:= P, R =/= error],
                  case lists:reverse(lists:keysort(#cell_inspect_inspection.id, Results)) of
                      [] -> not_found;
                      [#cell_inspect_inspection{id = Of} | _] ->
                          Id = new_id(),
                          ok = mnesia:write(#cell_inspect_override{
                                               id = Id, block = B, point = P, serial = S,
                                               employee = E, inspection = Of, time = Time}),
                          {ok, Id}
                  end
          end,
    case cell_db:sync_transaction(Fun) of
        {atomic, {ok, _} = Done} ->
            ok = history(S, inspection_override, #{block => B, point => P, employee => E}),
            Done;
        {atomic, Result} ->
            Result;
        {aborted, Why} ->
            {error, Why}
    end.

%% The part's history in the cell's traceability; a part without a serial has none.
history(<<>>, _What, _Detail) ->
    ok;
history(Serial, What, Detail) ->
    cell_stats:record(Serial, What, Detail).

%% @doc Everything recorded for a part serial, oldest first.
-spec by_serial(binary()) -> {ok, #{inspections := [map()], overrides := [map()]}}
                             | {error, term()}.
by_serial(Serial) ->
    Fun = fun() ->
                  {mnesia:index_read(?INSPECTIONS, Serial, #cell_inspect_inspection.serial),
                   mnesia:index_read(?OVERRIDES, Serial, #cell_inspect_override.serial)}
          end,
    case mnesia:transaction(Fun) of
        {atomic, {Is, Os}} ->
            {ok, #{inspections => [inspection_map(I)
                                   || I <- lists:keysort(#cell_inspect_inspection.id, Is)],
                   overrides => [override_map(O)
                                 || O <- lists:keysort(#cell_inspect_override.id, Os)]}};
        {aborted, Why} ->
            {error, Why}
    end.

inspection_map(#cell_inspect_inspection{id = Id, block = B, point = P, serial = S, result = R,
                                        code = C, text = T, client = Cl, image = Im,
                                        time = Time}) ->
    #{id => id_text(Id), block => B, point => P, serial => S, result => R, code => C,
      text => T, client => Cl, image => Im, time => Time}.

override_map(#cell_inspect_override{id = Id, block = B, point = P, serial = S, employee = E,
                                    inspection = Of, time = Time}) ->
    #{id => id_text(Id), block => B, point => P, serial => S, employee => E,
      inspection => id_text(Of), time => Time}.

%% Ids sort by time; the unique integer separates records of the same microsecond.
new_id() ->
    {os:system_time(microsecond), erlang:unique_integer([positive, monotonic])}.

id_text({T, U}) ->
    iolist_to_binary([integer_to_list(T), $-, integer_to_list(U)]).
