%% @doc Recipes as MTConnect assets (pure): each recipe `Products/<name>.zprd' is a
%% File asset (MTConnect 2.0 Assets) of category PROCESS and type PRODUCTION_PROGRAM,
%% with its size, its modification time as version, its description as a comment, and
%% the cell's own device as its destination. The document is written over several
%% lines, so it travels in the SHDR multiline form.
%%
%% The schema leaves `Destinations' out when it likes, but the reference agent
%% (cppagent) refuses a File asset without one, so every recipe names the cell it is
%% for.
-module(cell_shdr_assets).

-export([recipe/2, xml_escape/1, type/0]).

%% @doc The asset type the adapter publishes.
-spec type() -> binary().
type() -> <<"File">>.

%% @doc The File asset document of a recipe, for a device uuid.
-spec recipe(cell_recipe:info(), binary()) -> binary().
recipe(#{name := Name, description := Desc, author := Author, modified := Modified,
         bytes := Bytes}, Uuid) ->
    Time = cell_shdr_codec:timestamp(Modified),
    Comment = case {Desc, Author} of
                  {<<>>, <<>>} -> [];
                  _ -> [<<"  <FileComments>\n    <FileComment timestamp=\"">>, Time, <<"\">">>,
                        xml_escape(comment(Desc, Author)), <<"</FileComment>\n  </FileComments>\n">>]
              end,
    iolist_to_binary(
      [<<"<File assetId=\"">>, xml_escape(Name), <<"\" timestamp=\"">>, Time,
       <<"\" deviceUuid=\"">>, xml_escape(Uuid), <<"\" name=\"">>, xml_escape(Name),
       <<".zprd\" mediaType=\"application/zip\" applicationCategory=\"PROCESS\" "
         "applicationType=\"PRODUCTION_PROGRAM\" size=\"">>, integer_to_binary(Bytes),
       <<"\" versionId=\"">>, integer_to_binary(Modified), <<"\" state=\"PRODUCTION\">\n">>,
       <<"  <FileLocation href=\"Products/">>, xml_escape(uri_escape(Name)), <<".zprd\"/>\n">>,
       <<"  <Destinations>\n    <Destination>">>, xml_escape(Uuid), <<"</Destination>\n"
         "  </Destinations>\n">>,
       Comment,
       <<"  <CreationTime>">>, Time, <<"</CreationTime>\n">>,
       <<"  <ModificationTime>">>, Time, <<"</ModificationTime>\n">>,
       <<"</File>">>]).

comment(Desc, <<>>) -> Desc;
comment(<<>>, Author) -> <<"by ", Author/binary>>;
comment(Desc, Author) -> <<Desc/binary, " (by ", Author/binary, ")">>.

%% @doc Text as XML character data or an attribute value.
-spec xml_escape(binary()) -> binary().
xml_escape(B) ->
    << <<(case C of
              $& -> <<"&amp;">>;
              $< -> <<"&lt;">>;
              $> -> <<"&gt;">>;
              $" -> <<"&quot;">>;
              $' -> <<"&apos;">>;
              _ -> <<C>>
          end)/binary>> || <<C>> <= B >>.

uri_escape(Name) ->
    unicode:characters_to_binary(uri_string:quote(Name)).
