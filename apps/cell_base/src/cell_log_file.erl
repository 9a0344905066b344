%% @doc A lager backend writing one file a day into the cell's `Logs/' folder:
%% `log YYYY-MM-DD.log' (kind `task': what {@link cell_log} logs for operators) or
%% `trace YYYY-MM-DD.log' (kind `trace': trace messages and reports from OTP, such
%% as crash reports). The file changes at local midnight; each line is written at once
%% (no buffering), so a killed node loses no line it logged.
-module(cell_log_file).
-behaviour(gen_event).

-export([init/1, handle_event/2, handle_call/2, handle_info/2, terminate/2,
         code_change/3]).

-record(state, {dir :: file:filename(),
                kind :: task | trace,
                date :: calendar:date() | undefined,
                fd :: file:io_device() | undefined}).

-spec init([{dir, file:filename()} | {kind, task | trace}]) -> {ok, #state{}}.
init(Config) ->
    {dir, Dir} = lists:keyfind(dir, 1, Config),
    {kind, Kind} = lists:keyfind(kind, 1, Config),
    {ok, #state{dir = Dir, kind = Kind}}.

-spec handle_event(term(), #state{}) -> {ok, #state{}}.
handle_event({log, Msg}, State) ->
    %% A log handler is an isolation boundary: a message it cannot format is written
    %% as a note, never a crash (lager would reinstall the handler and log the crash,
    %% which this handler would then see again).
    try
        handle_log(Msg, State)
    catch
        Class:Reason ->
            Note = io_lib:format("unprintable log message: ~tp:~tp", [Class, Reason]),
            {ok, write(cell_log:format_line(#{time => os:system_time(millisecond),
                                              level => warning, source => <<"cell_log">>,
                                              text => iolist_to_binary(Note)}), State)}
    end;
handle_event(_Other, State) ->
    {ok, State}.

handle_log(Msg, State) ->
    Metadata = lager_msg:metadata(Msg),
    case {State#state.kind, proplists:get_value(cell_log, Metadata)} of
        {task, task} ->
            Line = proplists:get_value(cell_line, Metadata),
            {ok, write(cell_log:format_line(Line), State)};
        {trace, task} ->
            {ok, State};
        {trace, _} ->
            {ok, write(trace_line(Msg, Metadata), State)};
        {task, _} ->
            {ok, State}
    end.

-spec handle_call(term(), #state{}) -> {ok, term(), #state{}}.
handle_call(get_loglevel, State) ->
    {ok, lager_util:config_to_mask(debug), State};
handle_call({set_loglevel, _}, State) ->
    {ok, ok, State};
handle_call(_Request, State) ->
    {ok, {error, unknown_call}, State}.

-spec handle_info(term(), #state{}) -> {ok, #state{}}.
handle_info(_Info, State) ->
    {ok, State}.

-spec terminate(term(), #state{}) -> ok.
terminate(_Reason, #state{fd = undefined}) ->
    ok;
terminate(_Reason, #state{fd = Fd}) ->
    _ = file:close(Fd),
    ok.

-spec code_change(term(), #state{}, term()) -> {ok, #state{}}.
code_change(_OldVsn, State, _Extra) ->
    {ok, State}.

trace_line(Msg, Metadata) ->
    {Mega, Sec, Micro} = lager_msg:timestamp(Msg),
    Ms = (Mega * 1000000 + Sec) * 1000 + Micro div 1000,
    Source = case proplists:get_value(source, Metadata) of
                 undefined ->
                     case proplists:get_value(module, Metadata) of
                         undefined -> <<"otp">>;
                         Mod -> atom_to_binary(Mod, utf8)
                     end;
                 S -> S
             end,
    Text = unicode:characters_to_binary(lager_msg:message(Msg)),
    %% lager's own levels above error all count as errors for the reader.
    Level = case lager_msg:severity(Msg) of
                S2 when S2 =:= error; S2 =:= critical; S2 =:= alert; S2 =:= emergency -> error;
                warning -> warning;
                notice -> silent;
                info -> brief;
                debug -> verbose
            end,
    cell_log:format_line(#{time => Ms, level => Level, source => Source,
                           text => case Text of B when is_binary(B) -> B; _ -> <<"?">> end}).

write(Data, State0) ->
    State = open_for_today(State0),
    case State#state.fd of
        undefined -> State;
        Fd ->
            case file:write(Fd, Data) of
                ok -> State;
                {error, _} ->
                    %% A full or failing disk must not take logging down: drop the line,
                    %% reopen on the next one.
                    _ = file:close(Fd),
                    State#state{fd = undefined, date = undefined}
            end
    end.

open_for_today(#state{date = Date, fd = Fd} = State) ->
    {Today, _} = calendar:local_time(),
    case Today of
        Date when Fd =/= undefined ->
            State;
        _ ->
            _ = Fd =/= undefined andalso file:close(Fd),
            Path = filename:join(State#state.dir, cell_log:file_name(State#state.kind, Today)),
            case file:open(Path, [append, raw, binary]) of
                {ok, NewFd} -> State#state{date = Today, fd = NewFd};
                {error, _} -> State#state{date = undefined, fd = undefined}
            end
    end.
