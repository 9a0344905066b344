%% @doc A TwinCAT NC I interpolation channel as its ADS interface has it: the part
%% program a path becomes, the system service's file writes that put it on the
%% target, the channel's functions that load and run it, and its state decoded. Pure:
%% the channel process ({@link cell_hal_ads_channel}) sends the requests.
%%
%% Index groups, for the channel with id `Ch' (1–255), on the NC's AMS port 500:
%% <ul>
%% <li>`16#2100 + Ch' state: 1 the channel's error code (INT32), 3 the interpreter's
%%   state (UINT32);</li>
%% <li>`16#2200 + Ch' functions: 4 load a program by name (the file's path, a
%%   string), 2 start the interpreter, 16#10 reset the channel, 16#11 stop it;</li>
%% <li>`16#2300 + Ch' cyclic process data: 2 the path's speed override (UINT32,
%%   1000000 = 100 %), which the NC applies to the path at once, a program running or
%%   not.</li>
%% </ul>
%% The program is written as a file by the system service (AMS port 10000): 120 FOPEN
%% (read-write, the open mode and the path kind in the index offset, the name written,
%% the handle read), 123 FWRITE and 121 FCLOSE (read-write by handle).
%%
%% The program is DIN 66025 as the NC I interpreter reads it: the XY plane (G17),
%% millimetres (G71), absolute coordinates (G90); a line to the path's start, then a
%% G01 for each line and a G02 (clockwise) or G03 (counter-clockwise) for each arc
%% with its centre as I and J from the arc's start; the path velocity as F in mm/min;
%% M30 at the end. The channel's own path dynamics (acceleration, deceleration and
%% jerk of its parameters) apply: DIN 66025 carries no acceleration.
-module(cell_hal_ads_nci).

-export([program/3, file_writes/3, request/2, decode_state/1, decode_error/1, news/3]).

-export_type([request/0, itp_state/0, ctx/0]).

-define(IG_STATE, 16#2100).
-define(IG_FUNCTIONS, 16#2200).
-define(IG_CYCLIC, 16#2300).
%% 0x2100 + channel
-define(ERROR_CODE, 16#1).
-define(ITP_STATE, 16#3).
%% 0x2200 + channel
-define(START, 16#2).
-define(LOAD_BY_NAME, 16#4).
-define(RESET, 16#10).
-define(STOP, 16#11).
%% 0x2300 + channel
-define(OVERRIDE, 16#2).
%% The system service (AMS port 10000).
-define(FOPEN, 120).
-define(FCLOSE, 121).
-define(FWRITE, 123).
-define(FOPEN_WRITE, 16#2).
-define(FOPEN_BINARY, 16#10).
-define(PATH_GENERIC, 1).

-type u32() :: 0..16#FFFFFFFF.
-type request() :: {write, u32(), u32(), binary()}
                 | {read, u32(), u32(), pos_integer()}
                 | {read_write, u32(), u32(), non_neg_integer(), binary()}.
-type ctx() :: #{channel := 1..255}.
%% The interpreter's states as the channel reports them, in the few kinds a path's
%% follower needs: no program or reset (idle), a program loaded or run to its end
%% (ready), taking or running one (running), stopped by a fault (aborted).
-type itp_state() :: idle | ready | running | aborted | {other, u32()}.

%% @doc The part program of `Path' at the path velocity `Velocity' (mm/s), for a
%% channel of `N' axes (2: X and Y; 3: Z too).
-spec program(cell_hal_path:path(), number(), 2 | 3) -> binary().
program(Path, Velocity, N) ->
    F = [" F", num(Velocity * 60)],
    Start = cell_hal_path:start(Path),
    {Body, _} = lists:mapfoldl(fun(M, Here) -> {[block(M, Here, N), F], to(M)} end,
                               Start, cell_hal_path:moves(Path)),
    Lines = [<<"G17 G71 G90">>, ["G01 ", coords(Start, N), F] | Body] ++ [<<"M30">>],
    iolist_to_binary([["N", integer_to_list(10 * I), " ", L, "\n"]
                      || {I, L} <- lists:zip(lists:seq(1, length(Lines)), Lines)]).

block({line, To, _Role}, _Here, N) ->
    ["G01 ", coords(To, N)];
block({arc, To, {Cx, Cy, _}, Dir, _Role}, {X0, Y0, _}, N) ->
    %% I and J: the centre from the arc's start (where the block before ended).
    [case Dir of cw -> "G02 "; ccw -> "G03 " end, coords(To, N),
     " I", num(Cx - X0), " J", num(Cy - Y0)].

to({line, To, _}) -> To;
to({arc, To, _, _, _}) -> To.

coords({X, Y, Z}, 3) -> ["X", num(X), " Y", num(Y), " Z", num(Z)];
coords({X, Y, _}, 2) -> ["X", num(X), " Y", num(Y)].

num(X) ->
    io_lib:format("~.4f", [float(X)]).

%% @doc The system service's requests that write `Program' into the file `Name' on the
%% target (opened for writing, binary, by its full path): FOPEN, whose answer is the
%% handle the FWRITE and FCLOSE given by `Handle' then name.
-spec file_writes(open | {write, u32(), binary()} | {close, u32()}, binary(), ctx()) ->
          request().
file_writes(open, Name, _Ctx) ->
    {read_write, ?FOPEN, (?PATH_GENERIC bsl 16) bor ?FOPEN_WRITE bor ?FOPEN_BINARY, 4,
     <<Name/binary, 0>>};
file_writes({write, Handle, Program}, _Name, _Ctx) ->
    {read_write, ?FWRITE, Handle, 0, Program};
file_writes({close, Handle}, _Name, _Ctx) ->
    {read_write, ?FCLOSE, Handle, 0, <<>>}.

%% @doc One operation of the channel as an ADS request.
-spec request(reset | stop | start | {load, binary()} | {override, number()} | state
              | error_code, ctx()) -> request().
request(reset, #{channel := C}) -> {write, ?IG_FUNCTIONS + C, ?RESET, <<>>};
request(stop, #{channel := C}) -> {write, ?IG_FUNCTIONS + C, ?STOP, <<>>};
request(start, #{channel := C}) -> {write, ?IG_FUNCTIONS + C, ?START, <<>>};
request({load, Name}, #{channel := C}) ->
    {write, ?IG_FUNCTIONS + C, ?LOAD_BY_NAME, <<Name/binary, 0>>};
request({override, Pct}, #{channel := C}) ->
    {write, ?IG_CYCLIC + C, ?OVERRIDE, <<(round(Pct * 10000)):32/little>>};
request(state, #{channel := C}) -> {read, ?IG_STATE + C, ?ITP_STATE, 4};
request(error_code, #{channel := C}) -> {read, ?IG_STATE + C, ?ERROR_CODE, 4}.

%% @doc The interpreter's state from its UINT32 (ITP_STATE_*: 0 init failed, 1 idle,
%% 2 ready, 3–10 started, scanning, running, staying running, writing a table,
%% searching a line, at the end, single-block stop; 11–13 aborting, aborted, fault;
%% 14 reset; 15 stop; 16 waiting for a function; 17 flushing its buffers).
-spec decode_state(binary()) -> {ok, itp_state()} | {error, {bad_state, binary()}}.
decode_state(<<S:32/little>>) ->
    {ok, itp(S)};
decode_state(Bin) ->
    {error, {bad_state, Bin}}.

itp(1) -> idle;
itp(14) -> idle;
itp(15) -> idle;
itp(2) -> ready;
itp(S) when S >= 3, S =< 10; S =:= 16; S =:= 17 -> running;
itp(S) when S >= 11, S =< 13 -> aborted;
itp(S) -> {other, S}.

%% @doc The channel's error code from its INT32.
-spec decode_error(binary()) -> {ok, integer()} | {error, {bad_error_code, binary()}}.
decode_error(<<E:32/little-signed>>) -> {ok, E};
decode_error(Bin) -> {error, {bad_error_code, Bin}}.

%% @doc What a state read after the job's writes were answered means for the job
%% (`follow': the program started; `halt': the channel stopped and reset): the NC
%% shows a started program as running at once, so a program read as ready again ran
%% to its end, and one read as idle (or aborted without an error) was stopped or reset
%% by someone else.
-spec news(follow | halt, itp_state(), integer()) ->
          running | done | aborted | {error, integer()}.
news(_Job, _State, Error) when Error =/= 0 ->
    {error, Error};
news(follow, ready, 0) -> done;
news(follow, idle, 0) -> aborted;
news(follow, aborted, 0) -> aborted;
news(follow, _State, 0) -> running;
news(halt, running, 0) -> running;
news(halt, _State, 0) -> done.
