%% @doc One message the PLC may push to the block's clients (its MessageID, the
%% seed's MessageKey).
-module(cell_inspect_message_settings).
-behaviour(cell_settings_schema).

-export([name/0, fields/0]).

-spec name() -> inspect_message.
name() -> inspect_message.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => id, type => {integer, -32768, 32767}, default => 1,
       doc => <<"The MessageID the PLC writes.">>},
     #{name => text, type => {string, 256}, default => <<>>,
       doc => <<"What the clients show.">>},
     #{name => kind, type => {enum, [yes_no, ok, text, number, password]}, default => yes_no,
       doc => <<"The answers offered: Yes / No; OK; a text, a number or a password "
                "(written to MessageResult) or Cancel.">>}].
