%% @doc The block's tags as HAL IO points: an IO group module ({@link cell_hal_group})
%% with two forms, and the few conversions between a tag's value and its points.
%%
%% <b>`s7'</b> — the Siemens S7 UDT of the seed ({@link cell_inspect_udt}) in Modbus
%% holding registers from `base' (default 0): a BOOL is a bit of a register, an INT a
%% register, an S7 STRING two points: `<tag>_len' (register of the maximum and actual
%% length bytes) and `<tag>' (the characters, two a register, from the next register).
%% Options: `base', `unit' (the HAL's), `lengths' (`point_id', `serial', `employee',
%% `string', `result'; the seed's 16 and 48 by default).
%%
%% <b>`ads'</b> — the Allen-Bradley tag names of the seed as the members of one
%% structure on a Beckhoff PLC read over ADS: `MVSCAMERA.TRIGGERINSPECTION' and so on.
%% Options: `struct' (default `<<"MVSCAMERA">>'; `<<"MAIN.MVSCAMERA">>' under a
%% program), `lengths' (the seed's `DATA/16' and `DATA/32' by default). BOOL, INT and
%% STRING(N) are TwinCAT's own; the ADS driver reads the structure's members by symbol
%% (with device notifications where it offers them).
%%
%% Strings: the PLC holds one byte a character (Latin-1); the block works with UTF-8.
%% A character the PLC cannot hold is written as `?', and a string is cut to its tag's
%% length.
-module(cell_inspect_io).
-behaviour(cell_hal_group).

-export([points/1]).
-export([check_opts/1, lengths/1, input_points/1, tag_of/2, writes/3, read/3,
         normalize/3, to_plc/2, from_plc/1]).

-export_type([opts/0]).

-type opts() :: #{layout := s7 | ads, lengths := cell_inspect_udt:lengths(),
                  base => non_neg_integer(), unit => 0..255, struct => binary(),
                  input_struct => binary(), output_struct => binary()}.

-define(ADS_LENGTHS, #{point_id => 16, serial => 32, employee => 32, string => 32,
                       result => 32}).

%% @doc Checks a block's IO options and fills in the defaults. The first fault is
%% named: `{error, {bad_option, Key}}'.
-spec check_opts(term()) -> {ok, opts()} | {error, {bad_option, atom()}}.
check_opts(#{layout := s7} = O) ->
    check(O, [layout, base, unit, lengths],
          fun() ->
                  Base = maps:get(base, O, 0),
                  Unit = maps:get(unit, O, undefined),
                  case cell_inspect_udt:check_lengths(maps:get(lengths, O, #{})) of
                      _ when not is_integer(Base); Base < 0 -> {error, {bad_option, base}};
                      _ when Unit =/= undefined, not (is_integer(Unit) andalso Unit >= 0
                                                      andalso Unit =< 255) ->
                          {error, {bad_option, unit}};
                      {ok, L} ->
                          Size = cell_inspect_udt:size(cell_inspect_udt:layout(L)),
                          case Base + Size div 2 =< 65536 of
                              true ->
                                  {ok, maps:merge(#{layout => s7, base => Base, lengths => L},
                                                  maps:with([unit], O))};
                              false -> {error, {bad_option, base}}
                          end;
                      {error, _} = E -> E
                  end
          end);
check_opts(#{layout := ads} = O) ->
    check(O, [layout, struct, lengths],
          fun() ->
                  Struct = maps:get(struct, O, <<"MVSCAMERA">>),
                  Lengths = maps:merge(?ADS_LENGTHS, maps:get(lengths, O, #{})),
                  case cell_inspect_udt:check_lengths(Lengths) of
                      _ when not is_binary(Struct); Struct =:= <<>> ->
                          {error, {bad_option, struct}};
                      {ok, L} ->
                          {ok, #{layout => ads, struct => Struct, lengths => L,
                                 input_struct => Struct, output_struct => Struct}};
                      {error, _} = E -> E
                  end
          end);
check_opts(#{layout := _}) ->
    {error, {bad_option, layout}};
check_opts(O) when is_map(O) ->
    check_opts(O#{layout => s7});
check_opts(_) ->
    {error, {bad_option, io}}.

check(O, Known, Then) ->
    case [K || K <- maps:keys(O), not lists:member(K, Known)] of
        [] -> Then();
        [K | _] when is_atom(K) -> {error, {bad_option, K}};
        [_ | _] -> {error, {bad_option, io}}
    end.

%% @doc The string lengths in force.
-spec lengths(opts()) -> cell_inspect_udt:lengths().
lengths(#{lengths := L}) -> L.

%%====================================================================
%% The IO group
%%====================================================================

%% @doc The HAL points of one block (its group instance's options: {@link check_opts/1}).
-spec points(map()) -> [cell_hal_group:point_def()].
points(#{layout := s7, base := Base, lengths := L}) ->
    lists:append([s7_points(E, Base) || E <- cell_inspect_udt:layout(L)]);
points(#{layout := ads, struct := Struct, lengths := L}) ->
    [#{name => T, dir => cell_inspect_tags:dir(T), type => hal_type(T, L),
       address => <<Struct/binary, ".", (cell_inspect_tags:ab_name(T))/binary>>,
       caption => cell_inspect_tags:seed_name(T),
       field => <<".", (cell_inspect_tags:ab_name(T))/binary>>}
     || T <- cell_inspect_tags:all()].

s7_points(#{tag := T, kind := Kind, byte := B, bit := Bit} = E, Base) ->
    Dir = cell_inspect_tags:dir(T),
    Caption = cell_inspect_tags:seed_name(T),
    Address = cell_inspect_udt:address(E),
    R = Base + cell_inspect_udt:register(B),
    case Kind of
        bool ->
            [#{name => T, dir => Dir, type => bool, address => Address, caption => Caption,
               field => {holding_register, R, cell_inspect_udt:register_bit(B, Bit)}}];
        int ->
            [#{name => T, dir => Dir, type => int16, address => Address, caption => Caption,
               field => {holding_register, R}}];
        {string, N} ->
            [#{name => len_point(T), dir => Dir, type => uint16, address => Address,
               caption => <<Caption/binary, " (lengths)">>, field => {holding_register, R}},
             #{name => T, dir => Dir, type => {string, N},
               address => iolist_to_binary(["DBB", integer_to_list(B + 2)]),
               caption => Caption, field => {holding_register, R + 1}}]
    end.

hal_type(T, L) ->
    case cell_inspect_tags:kind(T) of
        bool -> bool;
        int -> int16;
        {string, Class} -> {string, maps:get(Class, L)}
    end.

%% The point holding an S7 STRING's length bytes.
len_point(inspection_point_id_echo) -> inspection_point_id_echo_len;
len_point(part_serial_echo) -> part_serial_echo_len;
len_point(employee_override_echo) -> employee_override_echo_len;
len_point(inspection_string) -> inspection_string_len;
len_point(inspection_point_id) -> inspection_point_id_len;
len_point(part_serial) -> part_serial_len;
len_point(override_employee_id) -> override_employee_id_len;
len_point(message_result) -> message_result_len.

%% @doc The HAL points that carry what the PLC writes.
-spec input_points(opts()) -> [atom()].
input_points(O) ->
    [P || #{name := P, dir := in} <- points(O)].

%% @doc The tag a HAL point belongs to.
-spec tag_of(opts(), atom()) -> {ok, cell_inspect_tags:tag()} | error.
tag_of(#{layout := s7}, P) ->
    case [T || T <- cell_inspect_tags:all(), is_string(T), len_point(T) =:= P] of
        [T] -> {ok, T};
        [] -> known(P)
    end;
tag_of(#{layout := ads}, P) ->
    known(P).

known(P) ->
    case lists:member(P, cell_inspect_tags:all()) of
        true -> {ok, P};
        false -> error
    end.

is_string(T) ->
    case cell_inspect_tags:kind(T) of
        {string, _} -> true;
        _ -> false
    end.

%% @doc The HAL writes that give an output tag a value, in the order to write them: an
%% S7 STRING's characters before its length, so that the length commits it.
-spec writes(opts(), cell_inspect_tags:out_tag(), cell_inspect_tags:value()) ->
          [{atom(), cell_hal_type:value()}].
writes(#{layout := Layout, lengths := L}, Tag, V) ->
    case cell_inspect_tags:kind(Tag) of
        {string, Class} ->
            N = maps:get(Class, L),
            Bytes = to_plc(V, N),
            case Layout of
                s7 -> [{Tag, Bytes}, {len_point(Tag), cell_inspect_udt:header(N, byte_size(Bytes))}];
                ads -> [{Tag, Bytes}]
            end;
        _ ->
            [{Tag, V}]
    end.

%% @doc A tag's value from the HAL's table (no process hop).
-spec read(opts(), atom(), cell_inspect_tags:tag()) ->
          {ok, cell_inspect_tags:value()} | {error, term()}.
read(#{layout := Layout, lengths := L}, Group, Tag) ->
    case cell_inspect_tags:kind(Tag) of
        {string, Class} when Layout =:= s7 ->
            N = maps:get(Class, L),
            case {cell_hal:read(Group, len_point(Tag)), cell_hal:read(Group, Tag)} of
                {{ok, Head}, {ok, Chars}} ->
                    %% The characters stop at the first NUL already (the HAL's STRING).
                    Value = cell_inspect_udt:string_value(N, <<(Head bsr 8), (Head band 255),
                                                               Chars/binary>>),
                    {ok, from_plc(Value)};
                {{error, _} = E, _} -> E;
                {_, {error, _} = E} -> E
            end;
        {string, _} ->
            case cell_hal:read(Group, Tag) of
                {ok, Chars} -> {ok, from_plc(Chars)};
                E -> E
            end;
        _ ->
            cell_hal:read(Group, Tag)
    end.

%% @doc A value as it reads back once the PLC holds it: a string cut to its length,
%% with `?' for what the PLC cannot hold.
-spec normalize(opts(), cell_inspect_tags:tag(), cell_inspect_tags:value()) ->
          cell_inspect_tags:value().
normalize(#{lengths := L}, Tag, V) ->
    case cell_inspect_tags:kind(Tag) of
        {string, Class} -> from_plc(to_plc(V, maps:get(Class, L)));
        _ -> V
    end.

%% @doc A UTF-8 string as a PLC holds it: one byte a character, at most `Max', no NUL.
-spec to_plc(binary(), pos_integer()) -> binary().
to_plc(V, Max) ->
    Chars = case unicode:characters_to_list(V, utf8) of
                L when is_list(L) -> L;
                _ -> binary_to_list(V)      %% not UTF-8: taken as bytes
            end,
    list_to_binary([if C >= 1, C =< 255 -> C; true -> $? end
                    || C <- lists:sublist(Chars, Max)]).

%% @doc A PLC's string (one byte a character) as UTF-8.
-spec from_plc(binary()) -> binary().
from_plc(Bytes) ->
    unicode:characters_to_binary(Bytes, latin1, utf8).
