; Inno Setup 6 script: the Windows installer of ElastoID.
;
; Build the onedir bundle first (dist\elastoid\ with elastoid.exe, elastoid-gui.exe and
; _internal\), then, from the repository root:
;
;   iscc /DAppVersion=0.1.0 packaging\windows\elastoid.iss
;
; which writes dist\installer\ElastoID-0.1.0-setup.exe. Relative paths below are
; relative to this script's folder. /DSourceDir=... picks another bundle folder.
;
; Installs into Program Files (64-bit), adds Start menu entries (the application, and
; a self-test that opens a console), an optional desktop icon, and an uninstaller
; (Settings > Apps). Per-user data (the mesh cache in %USERPROFILE%\.cache\elastoid,
; Qt settings in the registry) is left in place on uninstall.

#define AppName "ElastoID"
#ifndef AppVersion
  #define AppVersion "0.1.0"
#endif
#ifndef SourceDir
  #define SourceDir "..\..\dist\elastoid"
#endif

[Setup]
; the AppId identifies the installation for upgrades and the uninstaller: never change it
AppId={{5C0B7F0E-3D4A-4E51-9B8C-7A1E2F6D9C43}
AppName={#AppName}
AppVersion={#AppVersion}
AppVerName={#AppName} {#AppVersion}
AppPublisher=ElastoID
DefaultDirName={autopf}\{#AppName}
DefaultGroupName={#AppName}
DisableProgramGroupPage=yes
OutputDir=..\..\dist\installer
OutputBaseFilename={#AppName}-{#AppVersion}-setup
; the bundle is ~1.4 GB (MKL, VTK, Qt); LZMA compresses it ~5x (xz -6 of the Linux bundle: 282 MB)
Compression=lzma2
SolidCompression=yes
LZMAUseSeparateProcess=yes
ArchitecturesAllowed=x64compatible
ArchitecturesInstallIn64BitMode=x64compatible
PrivilegesRequired=admin
PrivilegesRequiredOverridesAllowed=dialog
MinVersion=10.0
WizardStyle=modern
UninstallDisplayName={#AppName} {#AppVersion}
UninstallDisplayIcon={app}\elastoid-gui.exe
; an upgrade replaces the old files while the app is closed
CloseApplications=yes

[Languages]
Name: "english"; MessagesFile: "compiler:Default.isl"

[Tasks]
Name: "desktopicon"; Description: "{cm:CreateDesktopIcon}"; GroupDescription: "{cm:AdditionalIcons}"; Flags: unchecked

[InstallDelete]
; an upgrade must not keep modules of the previous version next to the new ones
Type: filesandordirs; Name: "{app}\_internal"

[Files]
Source: "{#SourceDir}\*"; DestDir: "{app}"; Flags: ignoreversion recursesubdirs createallsubdirs

[Icons]
Name: "{autoprograms}\{#AppName}"; Filename: "{app}\elastoid-gui.exe"; WorkingDir: "{userdocs}"
Name: "{autoprograms}\{#AppName} self-test"; Filename: "{cmd}"; \
  Parameters: "/k """"{app}\elastoid.exe"" --selftest"""; WorkingDir: "{userdocs}"
Name: "{autodesktop}\{#AppName}"; Filename: "{app}\elastoid-gui.exe"; WorkingDir: "{userdocs}"; Tasks: desktopicon

[Run]
Filename: "{app}\elastoid-gui.exe"; Description: "{cm:LaunchProgram,{#AppName}}"; \
  Flags: nowait postinstall skipifsilent

[UninstallDelete]
; Python writes nothing into the bundle, but remove the folder if anything was left in it
Type: dirifempty; Name: "{app}"
